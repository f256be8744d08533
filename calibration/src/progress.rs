//! Progress of the slow steps (reading images, detecting the target in each view, optimising) on
//! the terminal: an indicatif bar on stderr, hidden when stderr is not a terminal (a pipe, a log
//! file, a test) or when the user asked for quiet, so logs and scripted runs stay clean.

use std::io::IsTerminal;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};

/// Where progress goes for one run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProgressSink {
    visible: bool,
}

impl ProgressSink {
    /// Bars on stderr when it is a terminal and `quiet` is false.
    pub fn terminal(quiet: bool) -> Self {
        Self {
            visible: !quiet && std::io::stderr().is_terminal(),
        }
    }

    /// No bars at all.
    pub fn hidden() -> Self {
        Self { visible: false }
    }

    /// A bar over `len` steps, e.g. one per image: `detecting ━━━━━━╸──── 12/40 views 0:03`.
    pub fn bar(&self, len: u64, message: &'static str, unit: &'static str) -> Progress {
        if !self.visible {
            return Progress {
                bar: ProgressBar::hidden(),
            };
        }
        let template = format!("{{msg:>12}} {{wide_bar}} {{pos}}/{{len}} {unit} {{elapsed}}");
        let style = ProgressStyle::with_template(&template)
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("━╸─");
        Progress {
            bar: ProgressBar::new(len)
                .with_style(style)
                .with_message(message),
        }
    }

    /// A spinner for a step of unknown length (an optimisation), ticking on its own.
    pub fn spinner(&self, message: &'static str) -> Progress {
        if !self.visible {
            return Progress {
                bar: ProgressBar::hidden(),
            };
        }
        let style = ProgressStyle::with_template("{spinner} {msg} {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_spinner());
        let bar = ProgressBar::new_spinner()
            .with_style(style)
            .with_message(message);
        bar.enable_steady_tick(Duration::from_millis(120));
        Progress { bar }
    }
}

/// One bar or spinner; cleared from the terminal when dropped.
#[derive(Debug)]
pub struct Progress {
    bar: ProgressBar,
}

impl Progress {
    /// One more step done.
    pub fn step(&self) {
        self.bar.inc(1);
    }

    pub fn position(&self) -> u64 {
        self.bar.position()
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hidden_bars_still_count() {
        let progress = ProgressSink::hidden().bar(3, "detecting", "views");
        progress.step();
        progress.step();
        assert_eq!(progress.position(), 2);
        assert!(progress.bar.is_hidden());
    }
}
