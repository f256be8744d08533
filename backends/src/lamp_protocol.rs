//! The pocket lamp's serial line protocol.
//!
//! The lamp's microcontroller writes one ASCII line per state report (any baud rate; 115200 8N1
//! is what the reference firmware uses), NMEA-style so that a terminal shows it readably:
//!
//! ```text
//! $RLAMP,<seq>,<on>,<level>,<cct>[,<qw>,<qx>,<qy>,<qz>]*<XX>\r\n
//! ```
//!
//! - `seq`: u32, +1 per report, wraps; a gap means lost lines.
//! - `on`: `0` or `1`.
//! - `level`: dimmer in [0, 1] (at most 4 decimals); radiant intensity = level × the lamp's
//!   calibrated maximum × the colour of `cct`.
//! - `cct`: correlated colour temperature, kelvin, integer in [1000, 20000].
//! - `qw,qx,qy,qz`: optional IMU orientation (unit quaternion, lamp body → world), omitted by
//!   lamps without an IMU.
//! - `XX`: two upper-case hex digits, the XOR of every byte between `$` and `*`.
//!
//! The lamp's *position* is not in the line: it comes from the marker on the lamp.
//!
//! [`LineParser`] takes bytes as they arrive (any split), resynchronises on `$`, and reports
//! each bad line as an error without losing the next good one: garbage, wrong checksums, lines
//! cut by an unplug, and the noise of a baud-rate mismatch (non-ASCII bytes, over-long lines).

use glam::{Quat, Vec3};
use relight_core::LampState;
use relight_core::light::blackbody_rgb;

/// Longest line accepted, `$` to `\n` (a full report is about 70 bytes).
pub const MAX_LINE: usize = 120;

const TALKER: &str = "RLAMP";

/// One report of the lamp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LampReport {
    pub seq: u32,
    pub on: bool,
    pub level: f32,
    pub cct_k: u32,
    pub orientation: Option<Quat>,
}

impl LampReport {
    /// The line the lamp writes for this report, checksum and `\r\n` included.
    pub fn to_line(&self) -> String {
        let mut body = format!(
            "{TALKER},{},{},{:.4},{}",
            self.seq,
            u8::from(self.on),
            self.level.clamp(0.0, 1.0),
            self.cct_k
        );
        if let Some(q) = self.orientation {
            body.push_str(&format!(",{:.5},{:.5},{:.5},{:.5}", q.w, q.x, q.y, q.z));
        }
        format!("${body}*{:02X}\r\n", checksum(body.as_bytes()))
    }

    /// The lamp as the pipeline sees it: this report at `position_in_world` (from its marker),
    /// with `max_intensity` the calibrated radiant intensity at level 1, W/sr (luminance).
    pub fn state(&self, position_in_world: Vec3, max_intensity: f32) -> LampState {
        let intensity = if self.on {
            blackbody_rgb(self.cct_k as f32) * (self.level * max_intensity)
        } else {
            Vec3::ZERO
        };
        LampState {
            on: self.on,
            position_in_world,
            intensity,
        }
    }
}

/// Why a line was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LineError {
    #[error("lamp line longer than {MAX_LINE} bytes (baud-rate mismatch?); skipped")]
    TooLong,
    #[error("lamp line holds non-ASCII bytes (baud-rate mismatch or noise); skipped")]
    NotAscii,
    #[error("lamp line `{line}`: checksum {found:02X}, computed {computed:02X}")]
    Checksum {
        line: String,
        found: u8,
        computed: u8,
    },
    #[error("lamp line `{line}`: {reason}")]
    Malformed { line: String, reason: String },
    #[error("lamp line cut off by `$` before its end: `{line}`")]
    Cut { line: String },
}

fn checksum(body: &[u8]) -> u8 {
    body.iter().fold(0, |acc, b| acc ^ b)
}

/// Parses `$…*XX` (without the line ending).
pub fn parse_line(line: &str) -> Result<LampReport, LineError> {
    let malformed = |reason: &str| LineError::Malformed {
        line: line.to_owned(),
        reason: reason.to_owned(),
    };
    let rest = line
        .strip_prefix('$')
        .ok_or_else(|| malformed("no leading `$`"))?;
    let (body, sum) = rest
        .rsplit_once('*')
        .ok_or_else(|| malformed("no `*` before the checksum"))?;
    // Two hex digits exactly: `from_str_radix` alone would also take a sign (`+A`).
    let found = (sum.len() == 2 && sum.bytes().all(|b| b.is_ascii_hexdigit()))
        .then(|| u8::from_str_radix(sum, 16).ok())
        .flatten()
        .ok_or_else(|| malformed("checksum is not two hex digits"))?;
    let computed = checksum(body.as_bytes());
    if found != computed {
        return Err(LineError::Checksum {
            line: line.to_owned(),
            found,
            computed,
        });
    }
    let fields: Vec<&str> = body.split(',').collect();
    if fields.first() != Some(&TALKER) {
        return Err(malformed("not an RLAMP sentence"));
    }
    if fields.len() != 5 && fields.len() != 9 {
        return Err(malformed("expected 4 or 8 fields after RLAMP"));
    }
    let seq = fields[1]
        .parse()
        .map_err(|_| malformed("seq is not a u32"))?;
    let on = match fields[2] {
        "0" => false,
        "1" => true,
        _ => return Err(malformed("on is not 0 or 1")),
    };
    let level: f32 = fields[3]
        .parse()
        .map_err(|_| malformed("level is not a number"))?;
    if !(0.0..=1.0).contains(&level) {
        return Err(malformed("level outside [0, 1]"));
    }
    let cct_k: u32 = fields[4]
        .parse()
        .map_err(|_| malformed("cct is not an integer"))?;
    if !(1000..=20_000).contains(&cct_k) {
        return Err(malformed("cct outside [1000, 20000] K"));
    }
    let orientation = if fields.len() == 9 {
        let mut q = [0f32; 4];
        for (v, field) in q.iter_mut().zip(&fields[5..]) {
            *v = field
                .parse()
                .map_err(|_| malformed("orientation is not four numbers"))?;
        }
        let q = Quat::from_xyzw(q[1], q[2], q[3], q[0]);
        if !q.is_finite() || (q.length() - 1.0).abs() > 1e-3 {
            return Err(malformed("orientation is not a unit quaternion"));
        }
        Some(q.normalize())
    } else {
        None
    };
    Ok(LampReport {
        seq,
        on,
        level,
        cct_k,
        orientation,
    })
}

/// Byte-stream parser: feed it whatever the serial port gave, in any split.
#[derive(Debug, Default)]
pub struct LineParser {
    line: Vec<u8>,
    /// Inside a line (after `$`).
    open: bool,
    /// Skipping the rest of an over-long or noisy line until its end.
    skipping: bool,
}

impl LineParser {
    pub fn new() -> Self {
        Self::default()
    }

    /// Feed bytes; every complete line (good or bad) yields one result, in order.
    pub fn push(&mut self, bytes: &[u8]) -> Vec<Result<LampReport, LineError>> {
        let mut out = Vec::new();
        for &b in bytes {
            match b {
                b'$' => {
                    if self.open && !self.skipping && !self.line.is_empty() {
                        out.push(Err(LineError::Cut {
                            line: String::from_utf8_lossy(&self.line).into_owned(),
                        }));
                    }
                    self.line.clear();
                    self.line.push(b);
                    self.open = true;
                    self.skipping = false;
                }
                b'\n' | b'\r' => {
                    if self.open && !self.skipping {
                        // Only ASCII bytes were kept, so this is valid UTF-8.
                        let line = String::from_utf8_lossy(&self.line).into_owned();
                        out.push(parse_line(&line));
                    }
                    self.line.clear();
                    self.open = false;
                    self.skipping = false;
                }
                _ if !self.open || self.skipping => {}
                _ if !(0x20..0x7f).contains(&b) => {
                    out.push(Err(LineError::NotAscii));
                    self.skipping = true;
                }
                _ if self.line.len() >= MAX_LINE => {
                    out.push(Err(LineError::TooLong));
                    self.skipping = true;
                }
                _ => self.line.push(b),
            }
        }
        out
    }

    /// Forget a partial line (after the port was closed and reopened).
    pub fn reset(&mut self) {
        *self = Self::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(seq: u32) -> LampReport {
        LampReport {
            seq,
            on: !seq.is_multiple_of(3),
            level: 0.25 * (seq % 5) as f32,
            cct_k: 2700 + 100 * seq,
            orientation: seq
                .is_multiple_of(2)
                .then(|| Quat::from_rotation_z(0.1 * seq as f32)),
        }
    }

    #[test]
    fn lines_round_trip() {
        for seq in 0..10 {
            let r = report(seq);
            let line = r.to_line();
            assert!(line.ends_with("\r\n") && line.len() < MAX_LINE, "{line}");
            let back = parse_line(line.trim_end()).unwrap();
            assert_eq!(
                (back.seq, back.on, back.level, back.cct_k),
                (r.seq, r.on, r.level, r.cct_k)
            );
            match (back.orientation, r.orientation) {
                (Some(a), Some(b)) => assert!(a.angle_between(b) < 1e-4),
                (None, None) => {}
                other => panic!("{other:?}"),
            }
        }
    }

    use glam::Vec4;

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig { cases: 256, failure_persistence: None, ..Default::default() })]

        /// Format → parse gives back any report the protocol can carry: level at its four
        /// decimals, orientation at its five (an angle within 1e-4 rad).
        #[test]
        fn any_report_round_trips(
            seq in proptest::prelude::any::<u32>(),
            on in proptest::prelude::any::<bool>(),
            level_e4 in 0u32..=10_000,
            cct_k in 1000u32..=20_000,
            axis in proptest::array::uniform3(-1.0f32..1.0),
            angle in -3.1f32..3.1,
            imu in proptest::prelude::any::<bool>(),
        ) {
            let axis = Vec3::from(axis);
            let orientation = (imu && axis.length() > 0.1)
                .then(|| Quat::from_axis_angle(axis.normalize(), angle));
            let report = LampReport { seq, on, level: level_e4 as f32 / 1e4, cct_k, orientation };
            let line = report.to_line();
            proptest::prop_assert!(line.len() < MAX_LINE, "{}", line);
            let back = parse_line(line.trim_end()).unwrap();
            proptest::prop_assert_eq!((back.seq, back.on, back.level, back.cct_k), (seq, on, report.level, cct_k));
            match (back.orientation, orientation) {
                // Five decimals per component (the f32 acos in angle_between is too coarse).
                (Some(a), Some(b)) => proptest::prop_assert!((Vec4::from(a) - Vec4::from(b)).abs().max_element() < 2e-5, "{a} {b}"),
                (None, None) => {}
                other => proptest::prop_assert!(false, "{other:?}"),
            }
        }

        /// Any text never panics the parser, and whatever it accepts writes back to a line it
        /// accepts again.
        #[test]
        fn any_text_parses_or_is_refused(line in "\\$RLAMP,[0-9]{1,10},[01],[0-9.]{1,7},[0-9]{3,6}(,[-0-9.]{1,8}){0,4}\\*[0-9A-Fa-f+-]{2}") {
            if let Ok(report) = parse_line(&line) {
                proptest::prop_assert!(parse_line(report.to_line().trim_end()).is_ok());
            }
        }
    }

    #[test]
    fn byte_by_byte_equals_all_at_once() {
        let stream: String = (0..6).map(|s| report(s).to_line()).collect();
        let mut whole = LineParser::new();
        let all = whole.push(stream.as_bytes());
        let mut split = LineParser::new();
        let mut bytes = Vec::new();
        for b in stream.as_bytes() {
            bytes.extend(split.push(std::slice::from_ref(b)));
        }
        assert_eq!(all, bytes);
        assert_eq!(all.len(), 6);
        assert!(all.iter().all(Result::is_ok));
    }

    #[test]
    fn garbage_bad_checksums_and_noise_cost_only_their_own_lines() {
        let good = |s| report(s).to_line();
        let mut corrupted = good(2).into_bytes();
        corrupted[8] ^= 0x01; // flip a bit in the body: checksum fails
        let mut stream = Vec::new();
        stream.extend(b"\x00\xff garbage before the first line ");
        stream.extend(good(1).as_bytes());
        stream.extend(&corrupted);
        stream.extend(b"$RLAMP,3,1,0.5"); // cut off by an unplug...
        stream.extend(good(4).as_bytes()); // ...and the next line after replug
        stream.extend(b"$\xf3\x9a\x11\xfe\xfe\r\n"); // baud mismatch noise
        stream.extend(vec![b'A'; 300]);
        stream.extend(b"$");
        stream.extend(vec![b'1'; 300]); // an endless line
        stream.extend(b"\n");
        stream.extend(good(5).as_bytes());
        stream.extend(b"$RLAMP,6,1,2.0,3000*");
        stream.extend(format!("{:02X}\r\n", checksum(b"RLAMP,6,1,2.0,3000")).as_bytes());

        let results = LineParser::new().push(&stream);
        let seqs: Vec<u32> = results
            .iter()
            .filter_map(|r| r.as_ref().ok())
            .map(|r| r.seq)
            .collect();
        assert_eq!(seqs, [1, 4, 5]);
        let errors: Vec<&LineError> = results.iter().filter_map(|r| r.as_ref().err()).collect();
        assert!(
            matches!(errors[0], LineError::Checksum { .. }),
            "{errors:?}"
        );
        assert!(matches!(errors[1], LineError::Cut { .. }), "{errors:?}");
        assert!(matches!(errors[2], LineError::NotAscii), "{errors:?}");
        assert!(matches!(errors[3], LineError::TooLong), "{errors:?}");
        assert!(
            matches!(errors[4], LineError::Malformed { reason, .. } if reason.contains("level")),
            "{errors:?}"
        );
        assert_eq!(errors.len(), 5);
    }

    #[test]
    fn a_checksum_with_a_sign_is_not_two_hex_digits() {
        let body = "RLAMP,1,1,0.5,3000";
        assert!(parse_line(&format!("${body}*{:02X}", checksum(body.as_bytes()))).is_ok());
        for signed in ["+A", "-A", " A", "+0"] {
            let line = format!("${body}*{signed}");
            assert!(
                matches!(parse_line(&line), Err(LineError::Malformed { reason, .. }) if reason.contains("two hex digits")),
                "{line}: {:?}",
                parse_line(&line)
            );
        }
    }

    #[test]
    fn state_scales_the_colour_temperature() {
        let mut r = report(1);
        r.on = true;
        r.level = 0.5;
        r.cct_k = 6504;
        let state = r.state(Vec3::Y, 4.0);
        let y =
            0.2126 * state.intensity.x + 0.7152 * state.intensity.y + 0.0722 * state.intensity.z;
        assert!((y - 2.0).abs() < 0.05, "{}", state.intensity);
        r.on = false;
        assert_eq!(r.state(Vec3::Y, 4.0).intensity, Vec3::ZERO);
    }
}
