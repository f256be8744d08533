//! The simulator's printed marker board: a rigid grid of `tag36h11` tags (codes from
//! [`relight_backends::markers::tag36h11`]) with the print's reflectance, so the rig can render it
//! and report each tag's true pose.

use glam::{Vec2, Vec3};
use relight_backends::markers::tag36h11::{TAG36H11, tag36h11_cells};
use relight_core::Pose;
use relight_core::recording::truth::MarkerTruth;

/// A planar board of `cols × rows` tags with consecutive IDs, as printed for a lab.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerBoard {
    pub first_id: u32,
    pub cols: u32,
    pub rows: u32,
    /// Edge of each tag's black square, metres.
    pub tag_size_m: f32,
    /// Distance between neighbouring tags' black squares, metres (≥ 2 cells keeps the quiet
    /// zones apart).
    pub gap_m: f32,
    /// Board frame: origin at the board's centre, tags in its x–y plane (+x right, +y up as
    /// printed), +z out of the print.
    pub world_from_board: Pose,
    /// Reflectance of the print's white and black (diffuse, grey).
    pub white_albedo: f32,
    pub black_albedo: f32,
}

impl MarkerBoard {
    /// The printed layout, as a rig's calibration carries it.
    pub fn layout(&self) -> relight_core::rig::BoardLayout {
        relight_core::rig::BoardLayout {
            family: TAG36H11.into(),
            first_id: self.first_id,
            cols: self.cols,
            rows: self.rows,
            tag_size_m: f64::from(self.tag_size_m),
            gap_m: f64::from(self.gap_m),
        }
    }

    /// Tags of the board, each with its true pose (row 0 at the top, IDs left to right).
    pub fn tags(&self) -> Vec<MarkerTruth> {
        let pitch = self.tag_size_m + self.gap_m;
        let (w, h) = (self.cols as f32 * pitch, self.rows as f32 * pitch);
        (0..self.rows)
            .flat_map(|r| (0..self.cols).map(move |c| (r, c)))
            .map(|(r, c)| {
                let centre = Vec3::new(
                    -w / 2.0 + (c as f32 + 0.5) * pitch,
                    h / 2.0 - (r as f32 + 0.5) * pitch,
                    0.0,
                );
                MarkerTruth {
                    family: TAG36H11.into(),
                    marker_id: self.first_id + r * self.cols + c,
                    world_from_marker: self.world_from_board
                        * Pose::new(glam::Quat::IDENTITY, centre),
                    size_m: self.tag_size_m,
                }
            })
            .collect()
    }

    /// Print reflectance at a point of the board plane (board frame, metres), `None` off the
    /// printed tags (including their quiet zones).
    pub fn albedo_at(&self, point_in_board: Vec2) -> Option<f32> {
        let pitch = self.tag_size_m + self.gap_m;
        let (w, h) = (self.cols as f32 * pitch, self.rows as f32 * pitch);
        let col = ((point_in_board.x + w / 2.0) / pitch).floor();
        let row = ((h / 2.0 - point_in_board.y) / pitch).floor();
        if !(col >= 0.0 && row >= 0.0 && col < self.cols as f32 && row < self.rows as f32) {
            return None;
        }
        let centre = Vec2::new(
            -w / 2.0 + (col + 0.5) * pitch,
            h / 2.0 - (row + 0.5) * pitch,
        );
        let cell = self.tag_size_m / 8.0;
        let local = point_in_board - centre;
        let cx = ((local.x + 5.0 * cell) / cell).floor();
        let cy = ((5.0 * cell - local.y) / cell).floor();
        if !(0.0..10.0).contains(&cx) || !(0.0..10.0).contains(&cy) {
            return None;
        }
        let id = self.first_id + row as u32 * self.cols + col as u32;
        let cells = tag36h11_cells(id)?;
        Some(if cells[cy as usize][cx as usize] {
            self.white_albedo
        } else {
            self.black_albedo
        })
    }

    /// Where a ray meets the board's plane, in board coordinates, and at what distance.
    pub fn hit(&self, origin: Vec3, dir: Vec3) -> Option<(f32, Vec2)> {
        let board_from_world = self.world_from_board.inverse();
        let o = board_from_world.transform_point(origin);
        let d = board_from_world.transform_vector(dir);
        if d.z.abs() < 1e-8 {
            return None;
        }
        let t = -o.z / d.z;
        (t > 0.0).then(|| (t, (o + d * t).truncate()))
    }
}

/// The four corners of a tag's black square in its marker frame, in the order detectors report
/// them (AprilTag: counter-clockwise from bottom-left as printed).
pub fn corners_in_marker(size_m: f32) -> [Vec3; 4] {
    let s = size_m / 2.0;
    [
        Vec3::new(-s, -s, 0.0),
        Vec3::new(s, -s, 0.0),
        Vec3::new(s, s, 0.0),
        Vec3::new(-s, s, 0.0),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;
    use relight_backends::markers::board::Board;

    #[test]
    fn detector_board_from_the_layout_matches_the_simulator_truth() {
        let sim = MarkerBoard {
            first_id: 4,
            cols: 3,
            rows: 2,
            tag_size_m: 0.08,
            gap_m: 0.02,
            world_from_board: Pose::new(Quat::from_rotation_y(0.3), Vec3::new(0.2, -0.1, -1.5)),
            white_albedo: 0.8,
            black_albedo: 0.05,
        };
        let board = Board::from_layout(&sim.layout()).unwrap();
        for truth in sim.tags() {
            let tag = board.tag(truth.marker_id).unwrap();
            let world_from_marker = sim.world_from_board * tag.board_from_marker;
            assert!(
                (world_from_marker.translation - truth.world_from_marker.translation).length()
                    < 1e-6
            );
            assert_eq!(tag.size_m, f64::from(truth.size_m));
        }
        assert_eq!(board.tags().len(), 6);
    }

    #[test]
    fn board_pattern_matches_tag_cells() {
        let board = MarkerBoard {
            first_id: 3,
            cols: 2,
            rows: 2,
            tag_size_m: 0.08,
            gap_m: 0.04,
            world_from_board: Pose::IDENTITY,
            white_albedo: 0.8,
            black_albedo: 0.05,
        };
        let tags = board.tags();
        assert_eq!(tags.len(), 4);
        assert_eq!(tags[3].marker_id, 6);
        let cell = 0.08 / 8.0;
        for tag in &tags {
            let cells = tag36h11_cells(tag.marker_id).unwrap();
            let centre = tag.world_from_marker.translation.truncate();
            for (r, row) in cells.iter().enumerate() {
                for (c, &white) in row.iter().enumerate() {
                    let p = centre + Vec2::new((c as f32 - 4.5) * cell, (4.5 - r as f32) * cell);
                    let expected = if white { 0.8 } else { 0.05 };
                    assert_eq!(
                        board.albedo_at(p),
                        Some(expected),
                        "tag {} cell {r},{c}",
                        tag.marker_id
                    );
                }
            }
        }
        assert_eq!(board.albedo_at(Vec2::new(1.0, 0.0)), None);
    }
}
