//! Per-stage timing statistics for status reports and the demo's summary.
//!
//! Each pipeline stage holds the [`StageTimer`] of its own name and records into it; status
//! reports read every timer through the [`Timings`] they were registered with.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};

use relight_engines::PassTiming;

use crate::control::types::StageTiming;
use crate::lock;

/// Running statistics of one stage: count, mean over all frames, and percentiles over the most
/// recent `window` frames (so a status report reflects the current behaviour).
#[derive(Debug, Clone)]
pub struct StageStats {
    pub name: String,
    frames: u64,
    total_ms: f64,
    last_ms: f64,
    recent: VecDeque<f64>,
    window: usize,
}

impl StageStats {
    pub fn new(name: impl Into<String>, window: usize) -> Self {
        Self {
            name: name.into(),
            frames: 0,
            total_ms: 0.0,
            last_ms: 0.0,
            recent: VecDeque::with_capacity(window),
            window: window.max(1),
        }
    }

    pub fn record(&mut self, ms: f64) {
        if !ms.is_finite() {
            return;
        }
        self.frames += 1;
        self.total_ms += ms;
        self.last_ms = ms;
        if self.recent.len() == self.window {
            self.recent.pop_front();
        }
        self.recent.push_back(ms);
    }

    pub fn frames(&self) -> u64 {
        self.frames
    }
    pub fn last_ms(&self) -> f64 {
        self.last_ms
    }
    pub fn mean_ms(&self) -> f64 {
        if self.frames == 0 {
            0.0
        } else {
            self.total_ms / self.frames as f64
        }
    }

    /// The largest value of the recent window (0 before the first), without sorting it.
    pub fn max_ms(&self) -> f64 {
        self.recent.iter().copied().fold(0.0, f64::max)
    }

    /// The `q`-quantile (0..=1) of the recent window, nearest-rank.
    pub fn quantile_ms(&self, q: f64) -> f64 {
        if self.recent.is_empty() {
            return 0.0;
        }
        let mut sorted: Vec<f64> = self.recent.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        let rank = (q.clamp(0.0, 1.0) * sorted.len() as f64).ceil() as usize;
        sorted[rank.saturating_sub(1).min(sorted.len() - 1)]
    }
}

/// The timers of a pipeline's stages, in the order they were first asked for.
#[derive(Debug)]
pub struct Timings {
    window: usize,
    timers: Mutex<Vec<StageTimer>>,
}

impl Timings {
    /// Percentiles over the most recent `window` frames of each stage.
    pub fn new(window: usize) -> Self {
        Self {
            window,
            timers: Mutex::new(Vec::new()),
        }
    }

    /// The timer of stage `name`, registered on first use.
    pub fn stage(&self, name: &str) -> StageTimer {
        let mut timers = lock(&self.timers);
        if let Some(timer) = timers.iter().find(|t| t.stats().name == name) {
            return timer.clone();
        }
        let timer = StageTimer(Arc::new(Mutex::new(StageStats::new(name, self.window))));
        timers.push(timer.clone());
        timer
    }

    /// Every stage that has timed a frame.
    pub fn report(&self) -> Vec<StageTiming> {
        lock(&self.timers)
            .iter()
            .map(StageTimer::stats)
            .filter(|s| s.frames() > 0)
            .map(|s| StageTiming {
                name: s.name.clone(),
                frames: s.frames(),
                last_ms: s.last_ms(),
                mean_ms: s.mean_ms(),
                p50_ms: s.quantile_ms(0.5),
                p99_ms: s.quantile_ms(0.99),
            })
            .collect()
    }
}

/// The passes of one stage as `<stage>.<pass>` timers (`render.gpu.shade`,
/// `depth.recon upload`), registered as they first appear.
#[derive(Debug)]
pub struct PassTimers {
    stage: &'static str,
    timings: Arc<Timings>,
    passes: Vec<(&'static str, StageTimer)>,
}

impl PassTimers {
    pub fn new(stage: &'static str, timings: Arc<Timings>) -> Self {
        Self {
            stage,
            timings,
            passes: Vec::new(),
        }
    }

    /// Record each pass of one frame.
    pub fn record(&mut self, passes: &[PassTiming]) {
        for &PassTiming { pass, ms } in passes {
            let index = match self.passes.iter().position(|(name, _)| *name == pass) {
                Some(index) => index,
                None => {
                    let timer = self.timings.stage(&format!("{}.{pass}", self.stage));
                    self.passes.push((pass, timer));
                    self.passes.len() - 1
                }
            };
            self.passes[index].1.record(ms);
        }
    }
}

/// One stage's statistics, shared between the stage that records and the status that reads.
#[derive(Debug, Clone)]
pub struct StageTimer(Arc<Mutex<StageStats>>);

impl StageTimer {
    pub fn record(&self, ms: f64) {
        lock(&self.0).record(ms);
    }

    pub fn stats(&self) -> MutexGuard<'_, StageStats> {
        lock(&self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_follow_the_recent_window() {
        let mut stats = StageStats::new("render", 100);
        for ms in 1..=100 {
            stats.record(f64::from(ms));
        }
        assert_eq!(stats.quantile_ms(0.5), 50.0);
        assert_eq!(stats.quantile_ms(0.99), 99.0);
        assert_eq!(stats.mean_ms(), 50.5);
        for _ in 0..100 {
            stats.record(2.0);
        }
        assert_eq!(stats.quantile_ms(0.99), 2.0);
        assert_eq!(stats.max_ms(), stats.quantile_ms(1.0));
        assert_eq!(stats.frames(), 200);
        stats.record(f64::NAN);
        assert_eq!(stats.frames(), 200);
    }

    #[test]
    fn a_stage_keeps_one_timer_and_reports_once_it_has_timed() {
        let timings = Timings::new(8);
        let render = timings.stage("render");
        timings.stage("output");
        render.record(3.0);
        timings.stage("render").record(5.0);
        let report = timings.report();
        assert_eq!(report.len(), 1, "output timed nothing");
        assert_eq!((report[0].name.as_str(), report[0].frames), ("render", 2));
        assert_eq!(report[0].mean_ms, 4.0);
    }
}
