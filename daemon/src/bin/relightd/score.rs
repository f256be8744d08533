//! `relightd score`: a simulated recording through the whole live path, scored against its
//! truth (`relight_daemon::score`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use relight_daemon::config::Config;
use relight_daemon::score::{ScoreSettings, default_config};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// A simulated recording with ground truth (`relightd simulate`).
    recording: PathBuf,
    /// The scene the recording was simulated from (its virtual object is inserted).
    #[arg(long)]
    scene: PathBuf,
    /// The engine to score.
    #[arg(long, default_value = "differential", value_parser = crate::engine_name())]
    engine: String,
    /// Engine parameters (`name=value`, repeatable).
    #[arg(long = "param")]
    params: Vec<String>,
    /// Samples per pixel of the truth's reference renders (`delta_truth_noise` says how much
    /// of `delta_rel_l2` is the truth's own noise).
    #[arg(long, default_value_t = 64)]
    reference_spp: u32,
    /// Where truth renders are kept between runs, keyed by the scene's files, each frame's true
    /// pose and lights, and the samples: a second run, of any engine, reads them back.
    #[arg(long, default_value = "target/bench/references")]
    reference_cache: PathBuf,
    /// Render every truth frame afresh (and keep none).
    #[arg(long)]
    no_reference_cache: bool,
    /// Write each scored frame's live, oracle and true composites here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the summary (median and p95 per measure) and the per-frame scores here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Take `[scene]`, `[tracking]` and `[sync]` from this configuration file (default: the
    /// built-in defaults).
    #[arg(long = "live-config")]
    live_config: Option<PathBuf>,
    /// Print the summary only, not the table per frame.
    #[arg(long)]
    summary: bool,
    /// Merge probe brackets and estimate the surface's albedo on threads of their own, as the
    /// daemon does, instead of inline in frame order: the scores then depend on thread timing,
    /// and the frames come as fast as they are scored, not at the sensor's rate.
    #[arg(long)]
    threads: bool,
}

pub fn run(args: Args) -> Result<()> {
    let config = match &args.live_config {
        Some(path) => Config::load(path)?,
        None => default_config(),
    };
    let settings = ScoreSettings {
        recording: args.recording,
        scene: args.scene,
        engine: args.engine,
        params: crate::params::parse_params(&args.params)?,
        reference_spp: args.reference_spp,
        reference_cache: (!args.no_reference_cache).then_some(args.reference_cache),
        out: args.out,
        config,
        threads: args.threads,
    };
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "scoring {bar:30} {pos}/{len} truth frames ({elapsed})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let report = relight_daemon::score::run(&settings, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    let table = report.table();
    match (args.summary, table.find("\n\n")) {
        (true, Some(end)) => print!("{}", &table[end + 2..]),
        _ => print!("{table}"),
    }
    if let Some(path) = args.json {
        std::fs::write(&path, serde_json::to_string_pretty(&report.to_json())?)
            .with_context(|| format!("writing {}", path.display()))?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
