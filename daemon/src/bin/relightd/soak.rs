//! `relightd soak`: a looped replay for a given time, watching the process's memory,
//! descriptors and threads (`relight_daemon::soak`).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Result;
use relight_daemon::config::Config;
use relight_daemon::soak::SoakSettings;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The recording replayed in a loop.
    recording: PathBuf,
    /// A scene directory, for the engines that need one.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Engines to run; with --switch-every, each in turn (repeatable or comma-separated).
    #[arg(long = "engine", value_delimiter = ',', default_value = "differential", value_parser = crate::engine_name())]
    engines: Vec<String>,
    /// How long to run.
    #[arg(long, default_value_t = 60.0)]
    seconds: f64,
    /// Switch to the next engine every this many seconds.
    #[arg(long)]
    switch_every: Option<f64>,
    /// Seconds between samples.
    #[arg(long, default_value_t = 10.0)]
    sample_every: f64,
    /// Growth is measured from the first sample after this many seconds.
    #[arg(long, default_value_t = 60.0)]
    warmup: f64,
    /// Write every sample and the summary here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Take `[scene]`, `[tracking]`, `[sync]` and the rest from this configuration file (its
    /// source and engine are replaced; default: the built-in defaults).
    #[arg(long = "live-config")]
    live_config: Option<PathBuf>,
}

pub fn run(args: Args) -> Result<()> {
    let positive = |name: &str, v: f64| {
        if v.is_finite() && v > 0.0 {
            Ok(Duration::from_secs_f64(v))
        } else {
            Err(anyhow::anyhow!(
                "--{name} must be a positive number of seconds"
            ))
        }
    };
    let settings = SoakSettings {
        recording: args.recording,
        scene: args.scene,
        engines: args.engines,
        duration: positive("seconds", args.seconds)?,
        switch_every: args
            .switch_every
            .map(|s| positive("switch-every", s))
            .transpose()?,
        sample_every: positive("sample-every", args.sample_every)?,
        warmup: Duration::try_from_secs_f64(args.warmup.max(0.0))
            .map_err(|_| anyhow::anyhow!("--warmup must be a finite number of seconds"))?,
        config: match &args.live_config {
            Some(path) => Config::load(path)?,
            None => Config {
                path: PathBuf::from("(relightd soak)"),
                ..Config::default()
            },
        },
    };
    println!(
        "{:>8} {:>9} {:>5} {:>7} {:>9} {:>8}  engine",
        "t s", "RSS MB", "fds", "threads", "frames", "switches"
    );
    let report = relight_daemon::soak::run(&settings, |s| {
        println!(
            "{:>8.1} {:>9.1} {:>5} {:>7} {:>9} {:>8}  {}",
            s.t_s,
            s.resources.rss_mb,
            s.resources.fds,
            s.resources.threads,
            s.frames_rendered,
            s.engine_switches,
            s.engine
        );
    })?;
    println!(
        "after {:.0} s of warm-up: RSS {:+.2} % (peak of the last fifth vs the first {:+.2} %), fds {:+}, threads {:+}",
        report.warmup_s,
        report.rss_growth_pct,
        report.rss_peak_growth_pct,
        report.fds_growth,
        report.threads_growth
    );
    if let Some(path) = args.json {
        relight_daemon::soak::write_json(&report, &path)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
