//! Printed fiducials for the simulated rig: AprilTag `tag36h11` codes and a rigid board of tags.
//!
//! The codes and their bit layout are those of the AprilTag 3 library (`tag36h11.c`, University
//! of Michigan, BSD-2; "an unlimited license is granted to use, adapt, modify, or embed the 2D
//! barcodes into any medium"), so images rendered here decode with libapriltag and OpenCV's
//! `DICT_APRILTAG_36h11`. Only the first [`TAG36H11_CODES`]`.len()` IDs are carried: a board and
//! a lamp marker need a few dozen, not 587.
//!
//! A tag is 10 × 10 cells: a white quiet zone (1 cell), a black border (1 cell) and 6 × 6 data
//! cells, white where the code's bit is set. Its size is the edge of the black square (8 cells),
//! as detectors report it.

use glam::{Vec2, Vec3};
use relight_core::Pose;
use relight_core::recording::truth::MarkerTruth;

/// The first 32 codes of AprilTag 3's `tag36h11` (IDs 0–31), most significant bit first.
pub const TAG36H11_CODES: [u64; 32] = [
    0x0000_000d_7e00_984b,
    0x0000_000d_da66_4ca7,
    0x0000_000d_c4a1_c821,
    0x0000_000e_17b4_70e9,
    0x0000_000e_f91d_01b1,
    0x0000_000f_429c_dd73,
    0x0000_0000_5da2_9225,
    0x0000_0001_106c_ba43,
    0x0000_0002_23be_d79d,
    0x0000_0002_1f51_213c,
    0x0000_0003_3eb1_9ca6,
    0x0000_0003_f76e_b0f8,
    0x0000_0004_69a9_7414,
    0x0000_0004_5dcf_e0b0,
    0x0000_0004_a646_5f72,
    0x0000_0005_1801_db96,
    0x0000_0005_eb94_6b4e,
    0x0000_0006_8a7c_c2ec,
    0x0000_0006_f0ba_2652,
    0x0000_0007_8765_559d,
    0x0000_0008_7b83_d129,
    0x0000_0008_6cc4_a5c5,
    0x0000_0008_b64d_f90f,
    0x0000_0009_c577_b611,
    0x0000_000a_3810_f2f5,
    0x0000_000a_f4d7_5b83,
    0x0000_000b_59a0_3fef,
    0x0000_000b_b109_6f85,
    0x0000_000d_1b92_fc76,
    0x0000_000d_0dd5_09d2,
    0x0000_000e_2cfd_a160,
    0x0000_0002_ff49_7c63,
];

/// (x, y) of data bit i (i = 0 is the code's most significant bit) in the 8 × 8 grid inside the
/// quiet zone, where 0 and 7 are the black border (AprilTag 3's `bit_x`, `bit_y`).
const TAG36H11_BITS: [(u8, u8); 36] = [
    (1, 1),
    (2, 1),
    (3, 1),
    (4, 1),
    (5, 1),
    (2, 2),
    (3, 2),
    (4, 2),
    (3, 3),
    (6, 1),
    (6, 2),
    (6, 3),
    (6, 4),
    (6, 5),
    (5, 2),
    (5, 3),
    (5, 4),
    (4, 3),
    (6, 6),
    (5, 6),
    (4, 6),
    (3, 6),
    (2, 6),
    (5, 5),
    (4, 5),
    (3, 5),
    (4, 4),
    (1, 6),
    (1, 5),
    (1, 4),
    (1, 3),
    (1, 2),
    (2, 5),
    (2, 4),
    (2, 3),
    (3, 4),
];

pub const TAG36H11: &str = "tag36h11";

/// Cells across a tag, quiet zone included.
pub const TAG_TOTAL_CELLS: u32 = 10;

/// The 10 × 10 cell pattern of `tag36h11` ID `id` (row-major, row 0 at the top; true = white),
/// or `None` for an ID this table does not carry.
pub fn tag36h11_cells(id: u32) -> Option<[[bool; 10]; 10]> {
    let code = *TAG36H11_CODES.get(id as usize)?;
    let mut cells = [[false; 10]; 10];
    for (i, row) in cells.iter_mut().enumerate() {
        for (j, cell) in row.iter_mut().enumerate() {
            *cell = i == 0 || i == 9 || j == 0 || j == 9;
        }
    }
    for (bit, &(x, y)) in TAG36H11_BITS.iter().enumerate() {
        if code & (1 << (35 - bit)) != 0 {
            cells[usize::from(y) + 1][usize::from(x) + 1] = true;
        }
    }
    Some(cells)
}

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

    #[test]
    fn codes_are_36_bits_and_far_apart() {
        for (i, a) in TAG36H11_CODES.iter().enumerate() {
            assert!(*a < 1 << 36);
            for b in &TAG36H11_CODES[i + 1..] {
                // The family's minimum Hamming distance is 11.
                assert!((a ^ b).count_ones() >= 11, "{a:x} {b:x}");
            }
        }
    }

    #[test]
    fn bit_layout_covers_every_data_cell_once() {
        let mut seen = [[false; 6]; 6];
        for &(x, y) in &TAG36H11_BITS {
            assert!((1..=6).contains(&x) && (1..=6).contains(&y));
            let cell = &mut seen[usize::from(y) - 1][usize::from(x) - 1];
            assert!(!*cell, "cell ({x}, {y}) twice");
            *cell = true;
        }
    }

    #[test]
    fn tag_has_quiet_zone_and_black_border() {
        let cells = tag36h11_cells(0).unwrap();
        let at = |r: usize, c: usize| cells[r][c];
        assert!((0..10).all(|k| at(0, k) && at(9, k) && at(k, 0) && at(k, 9)));
        assert!((1..9).all(|k| !at(1, k) && !at(8, k) && !at(k, 1) && !at(k, 8)));
        let white_data = (2..8)
            .flat_map(|r| (2..8).map(move |c| (r, c)))
            .filter(|&(r, c)| cells[r][c])
            .count();
        assert_eq!(white_data as u32, TAG36H11_CODES[0].count_ones());
        assert!(tag36h11_cells(32).is_none());
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
