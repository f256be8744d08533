//! HDR exposure bracketing on cameras whose exposure control takes effect some frames late.
//!
//! A camera streams continuously; writing its exposure control while frame `s` is being read
//! changes the sensor only for a later frame. UVC webcams (V4L2) and IDS uEye cameras in
//! freerun mode apply a new exposure one to three frames after the write, depending on where
//! in the frame period the write lands (the sensor is already integrating the next frame, and
//! rolling shutters mix the two exposures over one frame). With `latency_frames = L` meaning
//! "a write after frame `s` is in full effect from frame `s + 1 + L` on, and frames before may
//! carry the old exposure, the new one or a mix", [`ExposureSchedule`]:
//! - tags a frame only when the exposure in effect is certain — the last write is at least
//!   `L + 1` frames old — and drops the frames of the transition;
//! - when bracketing, writes the next exposure right after each kept frame, so a bracket of
//!   `n` exposures yields one tagged frame every `L + 1` frames and a full bracket every
//!   `n·(L + 1)` frames;
//! - counts frames by the device's sequence number, so frames the driver dropped still count
//!   towards the settling time;
//! - tags each frame with the exposure the device reported after the write (drivers round to
//!   their step), not with the one asked for.
//!
//! [`ExposureControl`] carries exposure requests from other threads (the control socket) to
//! the capture thread, which applies them between frames.

use std::sync::{Arc, Mutex, PoisonError};

/// The exposure plan and where the camera is in it. Pure: the device write is a closure.
#[derive(Debug, Clone)]
pub struct ExposureSchedule {
    latency_frames: u32,
    /// Exposures to cycle through, one per kept frame; a single entry is a fixed exposure.
    plan: Vec<u32>,
    /// Index in `plan` of the exposure written last.
    index: usize,
    /// The plan changed since the last write; restart it at the next frame.
    changed: bool,
    written: Option<Written>,
}

#[derive(Debug, Clone, Copy)]
struct Written {
    requested_us: u32,
    /// What the device reported after the write.
    applied_us: u32,
    /// First sequence number exposed with it for certain; `None` until the first frame after
    /// a write made before streaming started.
    effective_from: Option<u64>,
}

impl ExposureSchedule {
    /// A fixed exposure, with control writes taking effect `latency_frames` frames late.
    pub fn new(latency_frames: u32, exposure_us: u32) -> Self {
        Self {
            latency_frames,
            plan: vec![exposure_us],
            index: 0,
            changed: false,
            written: None,
        }
    }

    pub fn latency_frames(&self) -> u32 {
        self.latency_frames
    }

    /// The exposures planned: one (fixed) or the bracket.
    pub fn plan(&self) -> &[u32] {
        &self.plan
    }

    /// Replace the plan: a fixed exposure (one entry) or a bracket. Takes effect at the next
    /// frame, starting from the first entry. An empty plan is ignored.
    pub fn set_plan(&mut self, exposures_us: &[u32]) {
        if exposures_us.is_empty() || exposures_us == self.plan.as_slice() {
            return;
        }
        self.plan = exposures_us.to_vec();
        self.index = 0;
        self.changed = true;
    }

    /// Before streaming (re)starts: write the plan's first exposure. Frames are tagged from the
    /// first frame + `latency_frames` on.
    pub fn start<E>(&mut self, apply: impl FnOnce(u32) -> Result<u32, E>) -> Result<(), E> {
        self.index = 0;
        self.changed = false;
        let requested_us = self.plan[0];
        let applied_us = apply(requested_us)?;
        self.written = Some(Written {
            requested_us,
            applied_us,
            effective_from: None,
        });
        Ok(())
    }

    /// Frame `seq` arrived. Returns the exposure it was taken at, or `None` while a change is
    /// settling (drop the frame). May write the next exposure through `apply`, which returns
    /// the value the device actually applied.
    pub fn on_frame<E>(
        &mut self,
        seq: u64,
        apply: impl FnOnce(u32) -> Result<u32, E>,
    ) -> Result<Option<u32>, E> {
        let Some(written) = self.written.as_mut() else {
            return Ok(None);
        };
        let effective_from = *written
            .effective_from
            .get_or_insert(seq + u64::from(self.latency_frames));
        let tag = (seq >= effective_from).then_some(written.applied_us);
        let next = if self.changed {
            Some(0)
        } else if tag.is_some() && self.plan.len() > 1 {
            Some((self.index + 1) % self.plan.len())
        } else {
            None
        };
        if let Some(next) = next {
            self.changed = false;
            self.index = next;
            let requested_us = self.plan[next];
            if requested_us != written.requested_us {
                let applied_us = apply(requested_us)?;
                *written = Written {
                    requested_us,
                    applied_us,
                    effective_from: Some(seq + 1 + u64::from(self.latency_frames)),
                };
            }
        }
        Ok(tag)
    }
}

/// Exposure requests shared between the owner of a probe source and its capture thread.
#[derive(Debug, Clone)]
pub struct ExposureControl {
    inner: Arc<Mutex<Request>>,
}

#[derive(Debug, Default)]
struct Request {
    generation: u64,
    fixed_us: u32,
    bracket_us: Vec<u32>,
}

impl ExposureControl {
    /// Starts with a fixed exposure.
    pub fn new(exposure_us: u32) -> Self {
        Self {
            inner: Arc::new(Mutex::new(Request {
                generation: 0,
                fixed_us: exposure_us,
                bracket_us: Vec::new(),
            })),
        }
    }

    /// Fix the exposure (stops bracketing).
    pub fn set_exposure_us(&self, exposure_us: u32) {
        let mut request = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
        request.fixed_us = exposure_us;
        request.bracket_us.clear();
        request.generation += 1;
    }

    /// Cycle through `exposures_us`; empty returns to the last fixed exposure.
    pub fn set_bracketing(&self, exposures_us: &[u32]) {
        let mut request = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
        request.bracket_us = exposures_us.to_vec();
        request.generation += 1;
    }

    /// The plan now requested: the bracket, or the fixed exposure alone.
    pub fn plan(&self) -> Vec<u32> {
        let request = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
        Self::plan_of(&request)
    }

    /// The plan, when it changed since generation `seen` (which is updated).
    pub fn plan_if_changed(&self, seen: &mut u64) -> Option<Vec<u32>> {
        let request = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
        (request.generation != *seen).then(|| {
            *seen = request.generation;
            Self::plan_of(&request)
        })
    }

    fn plan_of(request: &Request) -> Vec<u32> {
        if request.bracket_us.is_empty() {
            vec![request.fixed_us]
        } else {
            request.bracket_us.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_pcg::Pcg64;
    use std::convert::Infallible;

    /// A camera whose exposure writes land `0..=max_delay` frames late (random per write), with
    /// the frames in between exposed at the old value, the new one, or a mix (`None`); drivers
    /// quantise exposures to 10 µs; `drop_rate` of the frames never reach the host (seq gaps).
    struct Camera {
        rng: Pcg64,
        max_delay: u64,
        drop_rate: f64,
        next_seq: u64,
        /// (first seq, exposure) of every write, in order; mixed frames precede each.
        writes: Vec<(u64, u32, u64)>,
    }

    impl Camera {
        fn new(seed: u64, max_delay: u64, drop_rate: f64) -> Self {
            Self {
                rng: Pcg64::seed_from_u64(seed),
                max_delay,
                drop_rate,
                next_seq: 1000,
                writes: Vec::new(),
            }
        }

        /// Write after the frames so far; returns the applied (quantised) exposure.
        fn write(&mut self, exposure_us: u32) -> Result<u32, Infallible> {
            let applied = exposure_us / 10 * 10;
            let delay = self.rng.random_range(0..=self.max_delay);
            let mixed_from = self.next_seq;
            self.writes
                .push((self.next_seq + delay, applied, mixed_from));
            Ok(applied)
        }

        /// The true exposure of frame `seq` (`None`: a mix of two).
        fn exposure_of(&self, seq: u64) -> Option<u32> {
            let mut exposure = None;
            for &(from, applied, mixed_from) in &self.writes {
                if seq >= from {
                    exposure = Some(applied);
                } else if seq >= mixed_from && self.max_delay > 0 {
                    // Transition: old, new or mixed; the worst case for a tagger is "mixed".
                    exposure = None;
                }
            }
            exposure
        }

        /// The next frame that reaches the host.
        fn next_frame(&mut self) -> u64 {
            while self.rng.random_bool(self.drop_rate) {
                self.next_seq += 1;
            }
            self.next_seq += 1;
            self.next_seq - 1
        }
    }

    /// Runs `frames` frames; returns (seq, tag, true exposure) of every tagged frame.
    fn run(
        schedule: &mut ExposureSchedule,
        camera: &mut Camera,
        frames: usize,
    ) -> Vec<(u64, u32, Option<u32>)> {
        let mut kept = Vec::new();
        for _ in 0..frames {
            let seq = camera.next_frame();
            let truth = camera.exposure_of(seq);
            if let Ok(Some(tag)) = schedule.on_frame(seq, |e| camera.write(e)) {
                kept.push((seq, tag, truth));
            }
        }
        kept
    }

    #[test]
    fn tags_match_the_exposure_in_effect_for_any_latency_up_to_the_bound() {
        for latency in 0..=3u32 {
            for (seed, drop_rate) in [(1, 0.0), (2, 0.2)] {
                let mut camera = Camera::new(seed, u64::from(latency), drop_rate);
                let mut schedule = ExposureSchedule::new(latency, 1_000);
                schedule.set_plan(&[250, 2_005, 16_000]);
                schedule.start(|e| camera.write(e)).unwrap();
                let kept = run(&mut schedule, &mut camera, 600);
                assert!(
                    kept.len() > 100,
                    "latency {latency}: only {} kept",
                    kept.len()
                );
                for (seq, tag, truth) in &kept {
                    assert_eq!(Some(*tag), *truth, "latency {latency}, frame {seq}");
                }
                // Quantised values are reported, the bracket is cycled in order.
                let tags: Vec<u32> = kept.iter().map(|k| k.1).collect();
                assert!(
                    tags.chunks_exact(3).all(|c| c == [250, 2_000, 16_000]),
                    "{tags:?}"
                );
            }
        }
    }

    #[test]
    fn a_bracket_yields_one_frame_per_latency_plus_one() {
        let latency = 2;
        let mut camera = Camera::new(5, latency, 0.0);
        let mut schedule = ExposureSchedule::new(latency as u32, 500);
        schedule.set_plan(&[100, 1_000]);
        schedule.start(|e| camera.write(e)).unwrap();
        let kept = run(&mut schedule, &mut camera, 300);
        let seqs: Vec<u64> = kept.iter().map(|k| k.0).collect();
        assert!(
            seqs.windows(2).all(|w| w[1] - w[0] == latency + 1),
            "{seqs:?}"
        );
        assert_eq!(seqs.len(), 100);
    }

    /// Guards the test itself: a tagger that underestimates the latency is caught.
    #[test]
    fn underestimating_the_latency_mis_tags_frames() {
        let mut camera = Camera::new(9, 2, 0.0);
        let mut schedule = ExposureSchedule::new(0, 500);
        schedule.set_plan(&[100, 1_000, 10_000]);
        schedule.start(|e| camera.write(e)).unwrap();
        let kept = run(&mut schedule, &mut camera, 300);
        let wrong = kept
            .iter()
            .filter(|(_, tag, truth)| Some(*tag) != *truth)
            .count();
        assert!(
            wrong > kept.len() / 2,
            "{wrong} of {} mis-tagged",
            kept.len()
        );
    }

    #[test]
    fn a_fixed_exposure_settles_once_and_then_tags_every_frame() {
        let mut camera = Camera::new(3, 1, 0.0);
        let mut schedule = ExposureSchedule::new(1, 4_000);
        schedule.start(|e| camera.write(e)).unwrap();
        let mut writes = 0;
        let mut tags = Vec::new();
        for _ in 0..20 {
            let seq = camera.next_frame();
            let tag = schedule
                .on_frame(seq, |e| {
                    writes += 1;
                    camera.write(e)
                })
                .unwrap();
            tags.push(tag);
        }
        assert_eq!(writes, 0, "a fixed exposure is written once, at start");
        assert_eq!(tags[0], None, "the first frame may predate the write");
        assert!(tags[1..].iter().all(|t| *t == Some(4_000)));

        // Changing it drops the transition, then tags the new value.
        schedule.set_plan(&[8_000]);
        let seq = camera.next_frame();
        assert_eq!(
            schedule.on_frame(seq, |e| camera.write(e)).unwrap(),
            Some(4_000)
        );
        let seq = camera.next_frame();
        assert_eq!(schedule.on_frame(seq, |e| camera.write(e)).unwrap(), None);
        let seq = camera.next_frame();
        assert_eq!(
            schedule.on_frame(seq, |e| camera.write(e)).unwrap(),
            Some(8_000)
        );
    }

    #[test]
    fn repeated_exposures_in_a_bracket_need_no_settling() {
        let mut camera = Camera::new(4, 2, 0.0);
        let mut schedule = ExposureSchedule::new(2, 100);
        schedule.set_plan(&[300, 300, 300]);
        schedule.start(|e| camera.write(e)).unwrap();
        let kept = run(&mut schedule, &mut camera, 12);
        assert_eq!(kept.len(), 10, "two settling frames, then every frame");
        assert!(
            kept.iter()
                .all(|(_, tag, truth)| *tag == 300 && *truth == Some(300))
        );
    }

    #[test]
    fn control_requests_reach_the_capture_side_once() {
        let control = ExposureControl::new(1_000);
        let mut seen = 0;
        assert_eq!(control.plan(), vec![1_000]);
        assert_eq!(control.plan_if_changed(&mut seen), None);
        control.set_bracketing(&[10, 100]);
        assert_eq!(control.plan_if_changed(&mut seen), Some(vec![10, 100]));
        assert_eq!(control.plan_if_changed(&mut seen), None);
        control.set_bracketing(&[]);
        assert_eq!(
            control.clone().plan_if_changed(&mut seen),
            Some(vec![1_000])
        );
        control.set_exposure_us(50);
        assert_eq!(control.plan_if_changed(&mut seen), Some(vec![50]));
    }
}
