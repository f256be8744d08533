//! `relightd soak`: the pipeline on a looped fast replay for a given time, optionally switching
//! engines every few seconds, sampling the process's resident memory, open descriptors and
//! threads. A leak shows as growth after the warm-up (the first minute by default: caches,
//! pools and the GPU driver's heaps fill up first); the summary gives it in percent.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use serde::Serialize;

use crate::config::{self, Config, ReplayConfig, SourceConfig};
use crate::pipeline::{Pipeline, PipelineOptions};

#[derive(Debug, Clone)]
pub struct SoakSettings {
    pub recording: PathBuf,
    pub scene: Option<PathBuf>,
    /// The engines to run, in turn; the first one alone without `switch_every`.
    pub engines: Vec<String>,
    pub duration: Duration,
    /// Switch to the next engine this often.
    pub switch_every: Option<Duration>,
    pub sample_every: Duration,
    /// Growth is measured from the first sample at or after this time.
    pub warmup: Duration,
    /// The rest of the configuration (`[scene]`, `[tracking]`, `[sync]`, …); its source,
    /// engine and scene directory are replaced.
    pub config: Config,
}

/// What the process holds at one moment.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Resources {
    pub rss_mb: f64,
    pub fds: usize,
    pub threads: usize,
}

impl Resources {
    /// This process's, from /proc.
    pub fn now() -> anyhow::Result<Self> {
        let status =
            std::fs::read_to_string("/proc/self/status").context("reading /proc/self/status")?;
        let field = |name: &str| -> anyhow::Result<f64> {
            status
                .lines()
                .find_map(|line| line.strip_prefix(name))
                .and_then(|rest| rest.split_whitespace().next())
                .and_then(|v| v.parse().ok())
                .with_context(|| format!("no {name} in /proc/self/status"))
        };
        Ok(Self {
            rss_mb: field("VmRSS:")? / 1024.0,
            threads: field("Threads:")? as usize,
            fds: std::fs::read_dir("/proc/self/fd")
                .context("reading /proc/self/fd")?
                .count(),
        })
    }
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SoakSample {
    pub t_s: f64,
    #[serde(flatten)]
    pub resources: Resources,
    pub engine: String,
    pub frames_rendered: u64,
    pub render_errors: u64,
    pub engine_switches: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct SoakReport {
    pub recording: PathBuf,
    pub engines: Vec<String>,
    pub switch_every_s: Option<f64>,
    pub warmup_s: f64,
    pub samples: Vec<SoakSample>,
    /// RSS growth from the first sample after the warm-up to the last, percent.
    pub rss_growth_pct: f64,
    /// Growth of the peak RSS: the highest sample of the last fifth of the run after the
    /// warm-up against the highest of its first fifth, percent. With engines switching, the
    /// endpoints may catch different engines (whose working sets differ by 100 MB); the peak of
    /// a window that holds every engine does not depend on which.
    pub rss_peak_growth_pct: f64,
    pub fds_growth: i64,
    pub threads_growth: i64,
}

/// Run the soak, calling `progress` with each sample as it is taken.
pub fn run(
    settings: &SoakSettings,
    mut progress: impl FnMut(&SoakSample),
) -> anyhow::Result<SoakReport> {
    let first = settings
        .engines
        .first()
        .context("soak needs at least one engine")?;
    let mut config = settings.config.clone();
    config.source = SourceConfig::Replay(ReplayConfig {
        path: settings.recording.clone(),
        mode: config::ReplayMode::Fast,
        loop_playback: true,
        speed: 1.0,
        topics: Default::default(),
    });
    config.engine.name.clone_from(first);
    config.scene.dir.clone_from(&settings.scene);
    let mut pipeline = Pipeline::start(config, PipelineOptions::default())?;
    let control = pipeline.control();
    let started = Instant::now();
    let mut samples = Vec::new();
    let mut next_sample = Duration::ZERO;
    let mut next_switch = settings.switch_every;
    let mut switches = 0u64;
    loop {
        let elapsed = started.elapsed();
        if let Some(at) = next_switch
            && elapsed >= at
            && let Some(every) = settings.switch_every
        {
            switches += 1;
            let name = &settings.engines[switches as usize % settings.engines.len()];
            control
                .engine_set(name)
                .map_err(|e| anyhow::anyhow!("engine set {name}: {}", e.message))?;
            next_switch = Some(at + every);
        }
        if elapsed >= next_sample {
            let status = pipeline.status();
            let sample = SoakSample {
                t_s: elapsed.as_secs_f64(),
                resources: Resources::now()?,
                engine: status.engine,
                frames_rendered: status.frames_rendered,
                render_errors: status.render_errors,
                engine_switches: switches,
            };
            progress(&sample);
            samples.push(sample);
            next_sample += settings.sample_every;
        }
        if elapsed >= settings.duration {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    pipeline.shutdown();
    Ok(report(settings, samples))
}

fn report(settings: &SoakSettings, samples: Vec<SoakSample>) -> SoakReport {
    let warmup_s = settings.warmup.as_secs_f64();
    let base = samples
        .iter()
        .find(|s| s.t_s >= warmup_s)
        .or(samples.last())
        .map(|s| s.resources);
    let last = samples.last().map(|s| s.resources);
    let (rss_growth_pct, fds_growth, threads_growth) = match (base, last) {
        (Some(base), Some(last)) => (
            100.0 * (last.rss_mb - base.rss_mb) / base.rss_mb.max(1e-9),
            last.fds as i64 - base.fds as i64,
            last.threads as i64 - base.threads as i64,
        ),
        _ => (0.0, 0, 0),
    };
    let after: Vec<f64> = samples
        .iter()
        .filter(|s| s.t_s >= warmup_s)
        .map(|s| s.resources.rss_mb)
        .collect();
    let window = after.len().div_ceil(5).max(1);
    let peak = |v: &[f64]| v.iter().copied().fold(f64::NAN, f64::max);
    let rss_peak_growth_pct = match (after.get(..window), after.len().checked_sub(window)) {
        (Some(first), Some(last_start)) => {
            let (first, last) = (peak(first), peak(&after[last_start..]));
            100.0 * (last - first) / first.max(1e-9)
        }
        _ => 0.0,
    };
    SoakReport {
        recording: settings.recording.clone(),
        engines: settings.engines.clone(),
        switch_every_s: settings.switch_every.map(|d| d.as_secs_f64()),
        warmup_s,
        samples,
        rss_growth_pct,
        rss_peak_growth_pct,
        fds_growth,
        threads_growth,
    }
}

/// Write `report` as JSON.
pub fn write_json(report: &SoakReport, path: &Path) -> anyhow::Result<()> {
    std::fs::write(path, serde_json::to_string_pretty(report)?)
        .with_context(|| format!("writing {}", path.display()))
}
