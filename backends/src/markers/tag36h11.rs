//! AprilTag `tag36h11`: the codes and their bit layout, as printed and as detected.
//!
//! The codes and their bit layout are those of the AprilTag 3 library (`tag36h11.c`, University
//! of Michigan, BSD-2; "an unlimited license is granted to use, adapt, modify, or embed the 2D
//! barcodes into any medium"), so patterns drawn from them decode with libapriltag and OpenCV's
//! `DICT_APRILTAG_36h11`. Only the first [`TAG36H11_CODES`]`.len()` IDs are carried: a board and
//! a lamp marker need a few dozen, not 587.
//!
//! A tag is 10 × 10 cells: a white quiet zone (1 cell), a black border (1 cell) and 6 × 6 data
//! cells, white where the code's bit is set. Its size is the edge of the black square (8 cells),
//! as detectors report it.

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
}
