//! Per-stage timing statistics for status reports and the demo's summary.

use std::collections::VecDeque;

/// Running statistics of one stage: count, mean over all frames, and percentiles over the most
/// recent `window` frames (so a status report reflects the current behaviour).
#[derive(Debug, Clone)]
pub struct StageStats {
    pub name: &'static str,
    frames: u64,
    total_ms: f64,
    last_ms: f64,
    recent: VecDeque<f64>,
    window: usize,
}

impl StageStats {
    pub fn new(name: &'static str, window: usize) -> Self {
        Self {
            name,
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
}
