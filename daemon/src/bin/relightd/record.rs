//! `relightd record`: the configured sources into an MCAP file, until a signal, a time limit or
//! the sources' end.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use relight_daemon::config::Config;
use relight_daemon::control::OutputRequest;
use relight_daemon::pipeline::{Pipeline, PipelineOptions};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The MCAP file to write (relative to the working directory).
    #[arg(long)]
    out: PathBuf,
    /// Replace OUT if it exists (it is refused otherwise).
    #[arg(long)]
    overwrite: bool,
    /// Stop after this many seconds (default: until SIGINT/SIGTERM or the sources end).
    #[arg(long)]
    seconds: Option<f64>,
}

pub fn run(args: Args, config_path: &Path) -> Result<()> {
    let limit = args
        .seconds
        .map(Duration::try_from_secs_f64)
        .transpose()
        .context("--seconds")?;
    let mut config = Config::load(config_path)?;
    config.recorder.autostart = false;
    let term = crate::serve::termination_flag()?;
    let options = PipelineOptions {
        exit_at_end: true,
        ..PipelineOptions::default()
    };
    let mut pipeline = Pipeline::start(config, options)?;
    let control = pipeline.control();
    control
        .record_start(OutputRequest {
            // Relative to where the command runs, not to the recorder directory.
            path: Some(std::path::absolute(&args.out).context("--out")?),
            overwrite: args.overwrite,
        })
        .map_err(|e| anyhow::anyhow!("{}", e.message))?;
    let started = Instant::now();
    while !term.load(Ordering::Acquire)
        && !pipeline.is_finished()
        && limit.is_none_or(|s| started.elapsed() < s)
    {
        std::thread::sleep(Duration::from_millis(20));
    }
    let summary = control
        .record_stop()
        .map_err(|e| anyhow::anyhow!("{}", e.message))?;
    pipeline.shutdown();
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}
