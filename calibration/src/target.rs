//! Calibration targets: a chessboard, a ChArUco board and a grid of AprilTags, each with its
//! 3-D points, its printed pattern (what [`crate::synth`] renders) and its place in the world.
//!
//! # Frames
//!
//! Every target's points live in its *target frame*, the frame OpenCV's chessboard uses: origin
//! at the first point, +X to the right and +Y down **as printed**, +Z into the print (a camera
//! that sees the print looks along +Z). Detected points carry the same ids whatever the target's
//! orientation in the image.
//!
//! relight's *board frame*, which defines the rig's world when a target is the world reference
//! (`RigCalibration::world_from_probe`), is the frame of `relight-backends`' marker boards: origin
//! at the centre of the pattern (the centre of its points' bounding box), +X right, +Y up as
//! printed, +Z out of the print. [`TargetGeometry::world_from_target`] maps one to the other.
//!
//! # Config (TOML)
//!
//! ```toml
//! kind = "chessboard"   # inner corners; exactly one of the two counts even
//! inner_cols = 9
//! inner_rows = 6
//! square_m = 0.03
//! ```
//! ```toml
//! kind = "charuco"      # OpenCV ChArUco: squares, square and marker edges
//! squares_x = 7
//! squares_y = 5
//! square_m = 0.04
//! marker_m = 0.03
//! dictionary = "aruco_4x4_50"
//! ```
//! ```toml
//! kind = "april_grid"   # tag36h11 (OpenCV's DICT_APRILTAG_36h11), IDs first_id.. row by row
//! cols = 6
//! rows = 4
//! tag_m = 0.04          # edge of each tag's black square
//! spacing_m = 0.012     # gap between neighbouring tags' black squares
//! first_id = 0
//! ```

use std::fmt;
use std::str::FromStr;

use glam::{DQuat, DVec2, DVec3};
use serde::{Deserialize, Serialize};

use crate::error::CalibrationError;
use crate::rigid::Rigid;

/// A calibration target, tagged by `kind` in TOML.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Target {
    Chessboard(Chessboard),
    Charuco(Charuco),
    AprilGrid(AprilGrid),
}

/// A chessboard counted by its inner corners (where four squares meet).
///
/// Exactly one of `inner_cols`, `inner_rows` must be even: otherwise the board looks the same
/// turned by 180° and its corner order (hence the pose of the world frame) is ambiguous.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Chessboard {
    /// Inner corners along a row (the printed board is `inner_cols + 1` squares wide).
    pub inner_cols: u32,
    /// Inner corners along a column.
    pub inner_rows: u32,
    /// Edge of one square, metres.
    pub square_m: f64,
}

/// An OpenCV ChArUco board: a chessboard with an ArUco marker in each white square. Corners are
/// identified by the markers around them, so partial views count and the orientation is never
/// ambiguous.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Charuco {
    /// Squares along the board's width and height.
    pub squares_x: u32,
    pub squares_y: u32,
    /// Edge of one chessboard square, metres.
    pub square_m: f64,
    /// Edge of one marker (its black border included), metres.
    pub marker_m: f64,
    #[serde(default = "default_charuco_dictionary")]
    pub dictionary: Dictionary,
}

/// A grid of AprilTags (`tag36h11`, decoded by OpenCV's `DICT_APRILTAG_36h11`), IDs `first_id`
/// onwards row by row from the top left; the four corners of every tag are points. Point id =
/// `4 × tag id + k`, k = 0..3 for the tag's top-left, top-right, bottom-right, bottom-left as
/// printed (OpenCV's corner order).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AprilGrid {
    pub cols: u32,
    pub rows: u32,
    /// Edge of each tag's black square, metres.
    pub tag_m: f64,
    /// Gap between neighbouring tags' black squares, metres.
    pub spacing_m: f64,
    #[serde(default)]
    pub first_id: u32,
}

fn default_charuco_dictionary() -> Dictionary {
    Dictionary::Aruco { bits: 4, count: 50 }
}

/// A square-marker dictionary of OpenCV's `aruco` module. Written as `aruco_4x4_50` …
/// `aruco_7x7_1000`, `aruco_original`, or the AprilTag families `tag16h5`, `tag25h9`,
/// `tag36h10`, `tag36h11` (the family names of `relight_core::MarkerDetection`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum Dictionary {
    /// `DICT_{bits}X{bits}_{count}`: bits 4–7, count 50, 100, 250 or 1000.
    Aruco {
        bits: u8,
        count: u16,
    },
    ArucoOriginal,
    AprilTag16h5,
    AprilTag25h9,
    AprilTag36h10,
    AprilTag36h11,
}

const ARUCO_COUNTS: [u16; 4] = [50, 100, 250, 1000];

impl Dictionary {
    /// OpenCV's `PREDEFINED_DICTIONARY_NAME` value.
    pub fn opencv_id(self) -> i32 {
        match self {
            Dictionary::Aruco { bits, count } => {
                let index = ARUCO_COUNTS.iter().position(|&c| c == count).unwrap_or(0);
                (i32::from(bits) - 4) * 4 + index as i32
            }
            Dictionary::ArucoOriginal => 16,
            Dictionary::AprilTag16h5 => 17,
            Dictionary::AprilTag25h9 => 18,
            Dictionary::AprilTag36h10 => 19,
            Dictionary::AprilTag36h11 => 20,
        }
    }

    /// Data bits along a marker's edge (the black border adds one cell on each side).
    pub fn marker_bits(self) -> u32 {
        match self {
            Dictionary::Aruco { bits, .. } => u32::from(bits),
            Dictionary::ArucoOriginal | Dictionary::AprilTag25h9 => 5,
            Dictionary::AprilTag16h5 => 4,
            Dictionary::AprilTag36h10 | Dictionary::AprilTag36h11 => 6,
        }
    }

    /// Number of distinct markers (IDs `0..count`).
    pub fn marker_count(self) -> u32 {
        match self {
            Dictionary::Aruco { count, .. } => u32::from(count),
            Dictionary::ArucoOriginal => 1024,
            Dictionary::AprilTag16h5 => 30,
            Dictionary::AprilTag25h9 => 35,
            Dictionary::AprilTag36h10 => 2320,
            Dictionary::AprilTag36h11 => 587,
        }
    }
}

impl fmt::Display for Dictionary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Dictionary::Aruco { bits, count } => write!(f, "aruco_{bits}x{bits}_{count}"),
            Dictionary::ArucoOriginal => f.write_str("aruco_original"),
            Dictionary::AprilTag16h5 => f.write_str("tag16h5"),
            Dictionary::AprilTag25h9 => f.write_str("tag25h9"),
            Dictionary::AprilTag36h10 => f.write_str("tag36h10"),
            Dictionary::AprilTag36h11 => f.write_str("tag36h11"),
        }
    }
}

impl FromStr for Dictionary {
    type Err = CalibrationError;
    /// Accepts relight's names and OpenCV's (`DICT_4X4_50`, `DICT_APRILTAG_36h11`), any case.
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let lower = text.trim().to_ascii_lowercase();
        let name = lower
            .strip_prefix("dict_")
            .unwrap_or(&lower)
            .replace("apriltag_", "tag");
        let unknown = || CalibrationError::UnknownDictionary(text.to_owned());
        match name.as_str() {
            "aruco_original" => return Ok(Dictionary::ArucoOriginal),
            "tag16h5" => return Ok(Dictionary::AprilTag16h5),
            "tag25h9" => return Ok(Dictionary::AprilTag25h9),
            "tag36h10" => return Ok(Dictionary::AprilTag36h10),
            "tag36h11" => return Ok(Dictionary::AprilTag36h11),
            _ => {}
        }
        let rest = name.strip_prefix("aruco_").unwrap_or(&name);
        let (size, count) = rest.split_once('_').ok_or_else(unknown)?;
        let (a, b) = size.split_once('x').ok_or_else(unknown)?;
        let bits: u8 = a.parse().map_err(|_| unknown())?;
        let count: u16 = count.parse().map_err(|_| unknown())?;
        if a != b || !(4..=7).contains(&bits) || !ARUCO_COUNTS.contains(&count) {
            return Err(unknown());
        }
        Ok(Dictionary::Aruco { bits, count })
    }
}

impl TryFrom<String> for Dictionary {
    type Error = CalibrationError;
    fn try_from(text: String) -> Result<Self, Self::Error> {
        text.parse()
    }
}

impl From<Dictionary> for String {
    fn from(dictionary: Dictionary) -> String {
        dictionary.to_string()
    }
}

impl Target {
    /// Parses a target from its TOML table (see the module docs).
    pub fn from_toml(text: &str) -> Result<Self, CalibrationError> {
        toml::from_str(text).map_err(|e| CalibrationError::InvalidTarget(e.to_string()))
    }

    /// A short description for messages, e.g. `chessboard 9x6`.
    pub fn describe(&self) -> String {
        match self {
            Target::Chessboard(c) => format!("chessboard {}x{}", c.inner_cols, c.inner_rows),
            Target::Charuco(c) => {
                format!("ChArUco {}x{} ({})", c.squares_x, c.squares_y, c.dictionary)
            }
            Target::AprilGrid(g) => format!("AprilTag grid {}x{} (tag36h11)", g.cols, g.rows),
        }
    }

    /// Checks sizes and counts; says which value is wrong.
    pub fn validate(&self) -> Result<(), CalibrationError> {
        let bad = |what: String| Err(CalibrationError::InvalidTarget(what));
        let positive = |name: &str, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(CalibrationError::InvalidTarget(format!(
                    "{name} must be a positive length in metres, got {value}"
                )))
            }
        };
        match self {
            Target::Chessboard(c) => {
                positive("square_m", c.square_m)?;
                if c.inner_cols < 2 || c.inner_rows < 2 {
                    return bad(format!(
                        "a chessboard needs at least 2x2 inner corners, got {}x{}",
                        c.inner_cols, c.inner_rows
                    ));
                }
                if c.inner_cols % 2 == c.inner_rows % 2 {
                    return bad(format!(
                        "chessboard {}x{}: exactly one inner-corner count must be even, or the \
                         board is symmetric under a half turn and its corner order ambiguous",
                        c.inner_cols, c.inner_rows
                    ));
                }
            }
            Target::Charuco(c) => {
                positive("square_m", c.square_m)?;
                positive("marker_m", c.marker_m)?;
                if c.squares_x < 2 || c.squares_y < 2 {
                    return bad(format!(
                        "a ChArUco board needs at least 2x2 squares, got {}x{}",
                        c.squares_x, c.squares_y
                    ));
                }
                if c.marker_m >= c.square_m {
                    return bad(format!(
                        "marker_m ({}) must be smaller than square_m ({})",
                        c.marker_m, c.square_m
                    ));
                }
                let markers = c.squares_x * c.squares_y / 2;
                if markers > c.dictionary.marker_count() {
                    return bad(format!(
                        "a {}x{} ChArUco board needs {markers} markers, {} has {}",
                        c.squares_x,
                        c.squares_y,
                        c.dictionary,
                        c.dictionary.marker_count()
                    ));
                }
            }
            Target::AprilGrid(g) => {
                positive("tag_m", g.tag_m)?;
                if !(g.spacing_m.is_finite() && g.spacing_m >= g.tag_m / 8.0) {
                    return bad(format!(
                        "spacing_m ({}) must leave at least one cell (tag_m / 8 = {}) of white \
                         between tags; two cells are better",
                        g.spacing_m,
                        g.tag_m / 8.0
                    ));
                }
                if g.cols == 0 || g.rows == 0 {
                    return bad(format!(
                        "an AprilTag grid needs tags, got {}x{}",
                        g.cols, g.rows
                    ));
                }
                let last = u64::from(g.first_id) + u64::from(g.cols) * u64::from(g.rows);
                if last > u64::from(Dictionary::AprilTag36h11.marker_count()) {
                    return bad(format!(
                        "tag36h11 has IDs 0..587; this grid needs {}..{last}",
                        g.first_id
                    ));
                }
            }
        }
        Ok(())
    }

    /// Points, edges, printed pattern and world frame of the target. ChArUco boards and AprilTag
    /// grids take their layout and marker bits from OpenCV (so that what is rendered is what
    /// OpenCV detects) and need the `opencv` feature.
    pub fn geometry(&self) -> Result<TargetGeometry, CalibrationError> {
        self.validate()?;
        match self {
            Target::Chessboard(c) => Ok(chessboard_geometry(self.clone(), c)),
            #[cfg(feature = "opencv")]
            Target::Charuco(c) => opencv_layout::charuco_geometry(self.clone(), c),
            #[cfg(feature = "opencv")]
            Target::AprilGrid(g) => opencv_layout::april_grid_geometry(self.clone(), g),
            #[cfg(not(feature = "opencv"))]
            Target::Charuco(_) | Target::AprilGrid(_) => Err(CalibrationError::NeedsOpenCv {
                what: "a marker target's layout",
            }),
        }
    }
}

/// A target's points (target frame, see the module docs), the pairs of points joined by a
/// printed edge, and its printed pattern.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetGeometry {
    target: Target,
    ids: Vec<u32>,
    points: Vec<DVec3>,
    edges: Vec<[u32; 2]>,
    print: Print,
    feature_m: f64,
    world_from_target: Rigid,
}

impl TargetGeometry {
    fn new(
        target: Target,
        mut points: Vec<(u32, DVec3)>,
        edges: Vec<[u32; 2]>,
        print: Print,
        feature_m: f64,
    ) -> Self {
        points.sort_by_key(|&(id, _)| id);
        let (min, max) = points.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), &(_, p)| (lo.min(p), hi.max(p)),
        );
        let centre = 0.5 * (min + max);
        let flip = DQuat::from_rotation_x(std::f64::consts::PI);
        let world_from_target = Rigid::new(flip, -(flip * centre));
        Self {
            target,
            ids: points.iter().map(|&(id, _)| id).collect(),
            points: points.into_iter().map(|(_, p)| p).collect(),
            edges,
            print,
            feature_m,
            world_from_target,
        }
    }

    pub fn target(&self) -> &Target {
        &self.target
    }

    /// Point ids, ascending.
    pub fn ids(&self) -> &[u32] {
        &self.ids
    }

    /// Points in the target frame, in the order of [`Self::ids`].
    pub fn points(&self) -> &[DVec3] {
        &self.points
    }

    /// The point with this id, if the target has it.
    pub fn point(&self, id: u32) -> Option<DVec3> {
        self.ids
            .binary_search(&id)
            .ok()
            .map(|index| self.points[index])
    }

    /// Pairs of point ids joined by a straight printed black/white edge (chessboard square
    /// sides, tag sides): where [`crate::views`] measures sharpness.
    pub fn edges(&self) -> &[[u32; 2]] {
        &self.edges
    }

    pub fn print(&self) -> &Print {
        &self.print
    }

    /// How far round each point the print shows nothing but that corner (no other corner, no
    /// marker bit), metres: the largest safe window for sub-pixel refinement.
    pub fn corner_clearance_m(&self) -> f64 {
        match &self.target {
            Target::Chessboard(c) => 0.45 * c.square_m,
            Target::Charuco(c) => 0.9 * (c.square_m - c.marker_m) / 2.0,
            Target::AprilGrid(g) => 0.9 * (g.tag_m / 8.0).min(g.spacing_m),
        }
    }

    /// Whether a view showing part of the target is usable: its points carry their own ids
    /// (ChArUco, AprilTag grid), unlike a chessboard's, which are numbered by their place in a
    /// fully seen grid.
    pub fn partial_views(&self) -> bool {
        !matches!(self.target, Target::Chessboard(_))
    }

    /// The pattern's feature size (square or tag edge), metres.
    pub fn feature_m(&self) -> f64 {
        self.feature_m
    }

    /// relight's board frame (origin at the pattern's centre, +Y up and +Z out of the print)
    /// from the target frame (+Y down, +Z into the print).
    pub fn world_from_target(&self) -> Rigid {
        self.world_from_target
    }

    /// The outline a detector needs to see: the points' bounding box grown by one feature
    /// (the outer squares or quiet zones), `per_edge` samples along each side, target frame.
    pub fn outline(&self, per_edge: usize) -> Vec<DVec3> {
        let (min, max) = self.points.iter().fold(
            (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(p.truncate()), hi.max(p.truncate())),
        );
        let grow = if matches!(self.target, Target::AprilGrid(_)) {
            0.25 * self.feature_m
        } else {
            self.feature_m
        };
        let (min, max) = (min - grow, max + grow);
        let corners = [min, DVec2::new(max.x, min.y), max, DVec2::new(min.x, max.y)];
        let per_edge = per_edge.max(1);
        (0..4)
            .flat_map(|side| {
                let (a, b) = (corners[side], corners[(side + 1) % 4]);
                (0..per_edge).map(move |i| a.lerp(b, i as f64 / per_edge as f64).extend(0.0))
            })
            .collect()
    }
}

/// The printed sheet: white paper over `[min, max]` (target frame, metres) with an optional
/// checkerboard and square markers on it. What [`crate::synth`] renders.
#[derive(Debug, Clone, PartialEq)]
pub struct Print {
    pub min: DVec2,
    pub max: DVec2,
    pub checker: Option<Checker>,
    pub markers: Vec<PrintedMarker>,
    buckets: Buckets,
}

/// Squares `(a, b)`, `0 ≤ a < squares_x`, `0 ≤ b < squares_y`, at `origin + (a, b) · square_m`;
/// black where `(a + b) % 2 == black_parity`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Checker {
    pub origin: DVec2,
    pub square_m: f64,
    pub squares_x: u32,
    pub squares_y: u32,
    pub black_parity: u32,
}

/// One square marker, axis-aligned in the target frame: `cells × cells` cells (its black border
/// included) from `top_left` (the marker's first corner, OpenCV's order), row-major from the top,
/// `true` = white.
#[derive(Debug, Clone, PartialEq)]
pub struct PrintedMarker {
    pub marker_id: u32,
    pub top_left: DVec2,
    pub size_m: f64,
    pub cells: u32,
    pub white: Vec<bool>,
}

/// Which markers overlap each cell of a coarse grid over the sheet, so a lookup touches one or
/// two markers instead of all of them.
#[derive(Debug, Clone, PartialEq, Default)]
struct Buckets {
    origin: DVec2,
    size_m: f64,
    cols: usize,
    rows: usize,
    markers: Vec<Vec<usize>>,
}

impl Print {
    fn new(min: DVec2, max: DVec2, checker: Option<Checker>, markers: Vec<PrintedMarker>) -> Self {
        let mut print = Self {
            min,
            max,
            checker,
            markers,
            buckets: Buckets::default(),
        };
        let size_m = print.markers.iter().map(|m| m.size_m).fold(0.0, f64::max);
        if size_m > 0.0 {
            let cols = ((max.x - min.x) / size_m).ceil().max(1.0) as usize;
            let rows = ((max.y - min.y) / size_m).ceil().max(1.0) as usize;
            let mut buckets = vec![Vec::new(); cols * rows];
            for (index, marker) in print.markers.iter().enumerate() {
                let lo = ((marker.top_left - min) / size_m).floor();
                let hi = ((marker.top_left + marker.size_m - min) / size_m).floor();
                for by in (lo.y.max(0.0) as usize)..=(hi.y.max(0.0) as usize).min(rows - 1) {
                    for bx in (lo.x.max(0.0) as usize)..=(hi.x.max(0.0) as usize).min(cols - 1) {
                        buckets[by * cols + bx].push(index);
                    }
                }
            }
            print.buckets = Buckets {
                origin: min,
                size_m,
                cols,
                rows,
                markers: buckets,
            };
        }
        print
    }

    /// Whether the print is white at a point of the target plane; `None` off the sheet.
    pub fn is_white(&self, point: DVec2) -> Option<bool> {
        if !(point.x >= self.min.x
            && point.y >= self.min.y
            && point.x < self.max.x
            && point.y < self.max.y)
        {
            return None;
        }
        if let Some(marker) = self.marker_at(point) {
            let cell = ((point - marker.top_left) / marker.size_m * f64::from(marker.cells))
                .floor()
                .clamp(DVec2::ZERO, DVec2::splat(f64::from(marker.cells - 1)));
            let index = cell.y as usize * marker.cells as usize + cell.x as usize;
            return Some(marker.white.get(index).copied().unwrap_or(true));
        }
        if let Some(checker) = &self.checker {
            let square = ((point - checker.origin) / checker.square_m).floor();
            if square.x >= 0.0
                && square.y >= 0.0
                && square.x < f64::from(checker.squares_x)
                && square.y < f64::from(checker.squares_y)
            {
                let parity = (square.x as u32 + square.y as u32) % 2;
                return Some(parity != checker.black_parity);
            }
        }
        Some(true)
    }

    fn marker_at(&self, point: DVec2) -> Option<&PrintedMarker> {
        let b = &self.buckets;
        if b.markers.is_empty() {
            return None;
        }
        let cell = ((point - b.origin) / b.size_m).floor();
        if cell.x < 0.0 || cell.y < 0.0 {
            return None;
        }
        let (bx, by) = (cell.x as usize, cell.y as usize);
        if bx >= b.cols || by >= b.rows {
            return None;
        }
        b.markers[by * b.cols + bx]
            .iter()
            .map(|&i| &self.markers[i])
            .find(|m| {
                let local = point - m.top_left;
                local.x >= 0.0 && local.y >= 0.0 && local.x < m.size_m && local.y < m.size_m
            })
    }
}

fn chessboard_geometry(target: Target, c: &Chessboard) -> TargetGeometry {
    let s = c.square_m;
    let id = |col: u32, row: u32| row * c.inner_cols + col;
    let mut points = Vec::new();
    let mut edges = Vec::new();
    for row in 0..c.inner_rows {
        for col in 0..c.inner_cols {
            points.push((
                id(col, row),
                DVec3::new(f64::from(col) * s, f64::from(row) * s, 0.0),
            ));
            if col + 1 < c.inner_cols {
                edges.push([id(col, row), id(col + 1, row)]);
            }
            if row + 1 < c.inner_rows {
                edges.push([id(col, row), id(col, row + 1)]);
            }
        }
    }
    // Squares from −s to inner·s; the square beyond corner 0 is black; one white square of
    // margin all round (the quiet zone detectors need).
    let checker = Checker {
        origin: DVec2::splat(-s),
        square_m: s,
        squares_x: c.inner_cols + 1,
        squares_y: c.inner_rows + 1,
        black_parity: 0,
    };
    let print = Print::new(
        DVec2::splat(-2.0 * s),
        DVec2::new(
            f64::from(c.inner_cols + 1) * s,
            f64::from(c.inner_rows + 1) * s,
        ),
        Some(checker),
        Vec::new(),
    );
    TargetGeometry::new(target, points, edges, print, s)
}

#[cfg(feature = "opencv")]
mod opencv_layout {
    //! ChArUco and AprilTag-grid layouts and marker bits, taken from OpenCV itself.

    use glam::DVec2;
    use opencv::aruco;
    use opencv::core::{Mat, Ptr};
    use opencv::prelude::*;

    use super::{
        AprilGrid, Charuco, Checker, Dictionary, Print, PrintedMarker, Target, TargetGeometry,
    };
    use crate::error::CalibrationError;

    pub(crate) fn dictionary(
        dictionary: Dictionary,
    ) -> Result<Ptr<aruco::Dictionary>, CalibrationError> {
        Ok(aruco::get_predefined_dictionary_i32(
            dictionary.opencv_id(),
        )?)
    }

    /// The cells of marker `id` (border of one black cell included), from `drawMarker` at one
    /// pixel per cell.
    fn marker_cells(
        dict: &Ptr<aruco::Dictionary>,
        dictionary: Dictionary,
        id: u32,
    ) -> Result<(u32, Vec<bool>), CalibrationError> {
        let cells = dictionary.marker_bits() + 2;
        let mut image = Mat::default();
        aruco::draw_marker(dict, id as i32, cells as i32, &mut image, 1)?;
        let bytes = image.data_bytes()?;
        if bytes.len() != (cells * cells) as usize {
            return Err(CalibrationError::InvalidTarget(format!(
                "OpenCV drew marker {id} of {dictionary} as {} pixels, expected {}",
                bytes.len(),
                cells * cells
            )));
        }
        Ok((cells, bytes.iter().map(|&b| b > 127).collect()))
    }

    pub(super) fn charuco_geometry(
        target: Target,
        c: &Charuco,
    ) -> Result<TargetGeometry, CalibrationError> {
        let dict = dictionary(c.dictionary)?;
        let board = aruco::CharucoBoard::create(
            c.squares_x as i32,
            c.squares_y as i32,
            c.square_m as f32,
            c.marker_m as f32,
            &dict,
        )?;
        let s = c.square_m;
        let height = f64::from(c.squares_y) * s;
        let marker_corners = board.obj_points();
        let marker_ids = board.ids();
        let first = marker_corners
            .get(0)
            .map_err(|_| CalibrationError::InvalidTarget("ChArUco board without markers".into()))?;
        // OpenCV's ChArUco frame has +Y down as printed in some releases and +Y up in others; a
        // marker's first corner is its top-left as printed and its fourth its bottom-left, which
        // says which. Bring everything into the target frame (+Y down, +Z into the print).
        let y_up = first.get(3)?.y < first.get(0)?.y;
        let to_target = |x: f64, y: f64| {
            if y_up {
                DVec2::new(x, height - y)
            } else {
                DVec2::new(x, y)
            }
        };
        let snap = |v: f64| (v / s).round() * s;

        let corners = board.chessboard_corners();
        let mut points = Vec::with_capacity(corners.len());
        for (id, corner) in corners.iter().enumerate() {
            let p = to_target(snap(f64::from(corner.x)), snap(f64::from(corner.y)));
            points.push((id as u32, p.extend(0.0)));
        }
        // Neighbouring ChArUco corners (one square apart) are joined by a square's side.
        let mut edges = Vec::new();
        for (i, &(a, pa)) in points.iter().enumerate() {
            for &(b, pb) in &points[i + 1..] {
                if ((pa - pb).length() - s).abs() < 1e-6 * s {
                    edges.push([a, b]);
                }
            }
        }

        let margin = (s - c.marker_m) / 2.0;
        let mut markers = Vec::with_capacity(marker_corners.len());
        let mut black_parity = None;
        for (index, quad) in marker_corners.iter().enumerate() {
            let id = marker_ids.get(index)? as u32;
            let q: Vec<DVec2> = quad
                .iter()
                .map(|p| to_target(f64::from(p.x), f64::from(p.y)))
                .collect();
            let centre = q.iter().copied().sum::<DVec2>() / q.len().max(1) as f64;
            let square = (centre / s).floor();
            let top_left = square * s + margin;
            // The quad must be the axis-aligned square this layout assumes, first corner at
            // its top left as printed.
            let expected = [
                top_left,
                top_left + DVec2::new(c.marker_m, 0.0),
                top_left + DVec2::splat(c.marker_m),
                top_left + DVec2::new(0.0, c.marker_m),
            ];
            let fits = q.len() == 4
                && q.iter()
                    .zip(expected)
                    .all(|(a, b)| a.distance(b) < 1e-5 + 1e-4 * s);
            if !fits {
                return Err(CalibrationError::InvalidTarget(format!(
                    "OpenCV's ChArUco marker {id} lies at {q:?}, not where a ChArUco layout \
                     puts it ({expected:?})"
                )));
            }
            // Markers sit in the white squares.
            black_parity.get_or_insert((square.x as u32 + square.y as u32 + 1) % 2);
            let (cells, white) = marker_cells(&dict, c.dictionary, id)?;
            markers.push(PrintedMarker {
                marker_id: id,
                top_left,
                size_m: c.marker_m,
                cells,
                white,
            });
        }
        let checker = Checker {
            origin: DVec2::ZERO,
            square_m: s,
            squares_x: c.squares_x,
            squares_y: c.squares_y,
            black_parity: black_parity.unwrap_or(0),
        };
        let quiet = 0.5 * s;
        let print = Print::new(
            DVec2::splat(-quiet),
            DVec2::new(f64::from(c.squares_x) * s, height) + quiet,
            Some(checker),
            markers,
        );
        Ok(TargetGeometry::new(target, points, edges, print, s))
    }

    pub(super) fn april_grid_geometry(
        target: Target,
        g: &AprilGrid,
    ) -> Result<TargetGeometry, CalibrationError> {
        let dictionary = Dictionary::AprilTag36h11;
        let dict = self::dictionary(dictionary)?;
        let pitch = g.tag_m + g.spacing_m;
        let mut points = Vec::new();
        let mut edges = Vec::new();
        let mut markers = Vec::new();
        for row in 0..g.rows {
            for col in 0..g.cols {
                let tag = g.first_id + row * g.cols + col;
                let top_left = DVec2::new(f64::from(col) * pitch, f64::from(row) * pitch);
                let corners = [
                    top_left,
                    top_left + DVec2::new(g.tag_m, 0.0),
                    top_left + DVec2::splat(g.tag_m),
                    top_left + DVec2::new(0.0, g.tag_m),
                ];
                for (k, corner) in corners.iter().enumerate() {
                    points.push((4 * tag + k as u32, corner.extend(0.0)));
                    edges.push([4 * tag + k as u32, 4 * tag + (k as u32 + 1) % 4]);
                }
                let (cells, white) = marker_cells(&dict, dictionary, tag)?;
                markers.push(PrintedMarker {
                    marker_id: tag,
                    top_left,
                    size_m: g.tag_m,
                    cells,
                    white,
                });
            }
        }
        // A white quiet zone of at least two cells (a quarter tag) round the outer tags.
        let quiet = g.spacing_m.max(0.25 * g.tag_m);
        let size = DVec2::new(
            f64::from(g.cols) * pitch - g.spacing_m,
            f64::from(g.rows) * pitch - g.spacing_m,
        );
        let print = Print::new(DVec2::splat(-quiet), size + quiet, None, markers);
        Ok(TargetGeometry::new(target, points, edges, print, g.tag_m))
    }
}

#[cfg(feature = "opencv")]
pub(crate) use opencv_layout::dictionary as opencv_dictionary;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dictionary_names_round_trip() {
        for text in [
            "aruco_4x4_50",
            "aruco_7x7_1000",
            "aruco_original",
            "tag36h11",
            "tag16h5",
        ] {
            let dictionary: Dictionary = text.parse().unwrap();
            assert_eq!(dictionary.to_string(), text);
        }
        assert_eq!(
            "DICT_APRILTAG_36h11".parse::<Dictionary>().unwrap(),
            Dictionary::AprilTag36h11
        );
        assert_eq!("DICT_5X5_100".parse::<Dictionary>().unwrap().opencv_id(), 5);
        assert_eq!(Dictionary::AprilTag36h11.opencv_id(), 20);
        assert!("aruco_4x5_50".parse::<Dictionary>().is_err());
        assert!("aruco_4x4_60".parse::<Dictionary>().is_err());
    }

    #[test]
    fn target_toml_layout() {
        let target = Target::from_toml(
            "kind = \"charuco\"\nsquares_x = 7\nsquares_y = 5\nsquare_m = 0.04\nmarker_m = 0.03\n",
        )
        .unwrap();
        let Target::Charuco(charuco) = target else {
            panic!("kind selects the ChArUco board");
        };
        assert_eq!(charuco.dictionary.to_string(), "aruco_4x4_50");
        let text = toml::to_string(&Target::Charuco(charuco)).unwrap();
        assert!(text.contains("dictionary = \"aruco_4x4_50\""), "{text}");
        assert!(
            Target::from_toml(
                "kind = \"chessboard\"\ninner_cols = 9\ninner_rows = 6\nsquare_m = 0.03\nsize = 2\n"
            )
            .is_err(),
            "unknown keys are refused"
        );
    }

    #[test]
    fn validation_names_the_problem() {
        let board = |cols, rows, square_m| {
            Target::Chessboard(Chessboard {
                inner_cols: cols,
                inner_rows: rows,
                square_m,
            })
        };
        assert!(board(9, 6, 0.03).validate().is_ok());
        let err = board(7, 7, 0.03).validate().unwrap_err().to_string();
        assert!(err.contains("half turn"), "{err}");
        let err = board(9, 6, -1.0).validate().unwrap_err().to_string();
        assert!(err.contains("square_m"), "{err}");
        let grid = Target::AprilGrid(AprilGrid {
            cols: 30,
            rows: 20,
            tag_m: 0.02,
            spacing_m: 0.005,
            first_id: 0,
        });
        assert!(grid.validate().unwrap_err().to_string().contains("587"));
    }

    #[test]
    fn chessboard_points_print_and_world_frame() {
        let geometry = Target::Chessboard(Chessboard {
            inner_cols: 9,
            inner_rows: 6,
            square_m: 0.03,
        })
        .geometry()
        .unwrap();
        assert_eq!(geometry.ids().len(), 54);
        assert_eq!(geometry.point(10), Some(DVec3::new(0.03, 0.03, 0.0)));
        assert_eq!(geometry.edges().len(), 8 * 6 + 9 * 5);
        let print = geometry.print();
        // The square beyond corner 0 is black, its neighbours white, the margin white.
        assert_eq!(print.is_white(DVec2::new(-0.015, -0.015)), Some(false));
        assert_eq!(print.is_white(DVec2::new(0.015, -0.015)), Some(true));
        assert_eq!(print.is_white(DVec2::new(0.015, 0.015)), Some(false));
        assert_eq!(print.is_white(DVec2::new(-0.045, 0.1)), Some(true));
        assert_eq!(print.is_white(DVec2::new(-0.07, 0.1)), None);
        // Board frame: centre of the corners at the origin, +Y up, +Z out of the print.
        let world_from_target = geometry.world_from_target();
        let corner0 = world_from_target.transform_point(DVec3::ZERO);
        assert!(corner0.distance(DVec3::new(-0.12, 0.075, 0.0)) < 1e-12);
        let into_print = world_from_target.transform_vector(DVec3::Z);
        assert!(into_print.distance(DVec3::NEG_Z) < 1e-12);
    }
}
