//! The Kinect v1 frame clock: frame `seq` and `device_ns` from the 32-bit timestamps the
//! camera puts in every frame.
//!
//! The Kinect stamps depth and colour frames with one free-running 32-bit counter at 60 MHz
//! (OpenKinect protocol documentation; libfreenect PR #465), which wraps every 71.6 s. A
//! stream's clock unwraps it into 64 bits and counts frames from it: a gap of k nominal frame
//! periods advances `seq` by k, so frames lost on the USB bus show as gaps downstream.

/// Ticks per second of the Kinect's frame clock.
pub const KINECT_CLOCK_HZ: u64 = 60_000_000;

/// One stream's clock. `seq` keeps increasing across reconnects; the unwrapped device time
/// continues by one nominal period over a reconnect, since a re-plugged Kinect restarts its
/// counter.
#[derive(Debug, Clone)]
pub(super) struct StreamClock {
    ticks_per_frame: u64,
    last_ticks: Option<u32>,
    /// Unwrapped ticks of the last frame.
    total_ticks: u64,
    /// `seq` of the last frame; `None` before the first.
    seq: Option<u64>,
}

impl StreamClock {
    /// A clock for a stream of `framerate` frames per second.
    pub(super) fn new(framerate: u32) -> Self {
        Self {
            ticks_per_frame: KINECT_CLOCK_HZ / u64::from(framerate.max(1)),
            last_ticks: None,
            total_ticks: 0,
            seq: None,
        }
    }

    /// The device was reopened: its counter starts afresh.
    pub(super) fn new_session(&mut self) {
        self.last_ticks = None;
    }

    /// `(seq, device_ns)` of a frame stamped `ticks`.
    pub(super) fn frame(&mut self, ticks: u32) -> (u64, u64) {
        let (advance_frames, advance_ticks) = match (self.seq, self.last_ticks) {
            (None, _) => {
                self.total_ticks = u64::from(ticks);
                (0, 0)
            }
            (Some(_), None) => (1, self.ticks_per_frame),
            (Some(_), Some(last)) => {
                let delta = u64::from(ticks.wrapping_sub(last));
                if delta == 0 || delta > u64::from(u32::MAX / 2) {
                    // A repeated or backwards stamp (a replay starting over): count one frame.
                    (1, self.ticks_per_frame)
                } else {
                    let frames = ((delta + self.ticks_per_frame / 2) / self.ticks_per_frame).max(1);
                    (frames, delta)
                }
            }
        };
        let seq = self.seq.map_or(0, |s| s + advance_frames);
        self.seq = Some(seq);
        self.total_ticks += advance_ticks;
        self.last_ticks = Some(ticks);
        // 1 tick = 50/3 ns.
        (seq, self.total_ticks * 50 / 3)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_count_from_zero_and_time_follows_the_60_mhz_counter() {
        let mut clock = StreamClock::new(30);
        assert_eq!(clock.frame(3_000_000), (0, 50_000_000));
        assert_eq!(clock.frame(5_000_000), (1, 83_333_333));
        assert_eq!(clock.frame(7_000_001), (2, 116_666_683));
    }

    #[test]
    fn wrap_around_is_unwrapped_and_gaps_advance_seq() {
        let mut clock = StreamClock::new(30);
        let start = u32::MAX - 1_000_000;
        let (_, t0) = clock.frame(start);
        // Across the wrap: one period.
        let (seq, t1) = clock.frame(start.wrapping_add(2_000_000));
        assert_eq!(seq, 1);
        assert_eq!(t1 - t0, 33_333_333);
        // Three periods later: two frames were lost.
        let (seq, t2) = clock.frame(start.wrapping_add(8_000_000));
        assert_eq!(seq, 4);
        assert_eq!(t2 - t0, 133_333_333);
    }

    #[test]
    fn a_reconnect_or_a_restarted_counter_continues_by_one_frame() {
        let mut clock = StreamClock::new(30);
        clock.frame(40_000_000);
        let (_, before) = clock.frame(42_000_000);
        clock.new_session();
        let (seq, after) = clock.frame(17);
        assert_eq!((seq, after - before), (2, 33_333_333));
        // Backwards without a reconnect (a looping replay): also one frame.
        let (seq, later) = clock.frame(5);
        assert_eq!((seq, later - after), (3, 33_333_333));
    }
}
