//! relightd: the relight service, and the tools around it.
//!
//! `relightd [--config FILE]` runs the configured pipeline as a service (systemd Type=notify);
//! `relightd replay FILE` plays a recording through the pipeline without a configuration file
//! (the demo); `relightd record` captures the configured sources to an MCAP file;
//! `relightd simulate` renders a scene through the simulated rig into a recording with ground
//! truth (how the demo recording is made); `relightd score` replays such a recording through the
//! live path and scores it against its truth; `relightd render` renders an offline scene with an
//! engine; `relightd bench` times and scores every engine; `relightd soak` watches resources
//! over a long replay; `relightd check-config` validates a configuration file; `relightd
//! recording check|repair` inspects and repairs recordings; `relightd gpu` lists adapters.
//!
//! `main` only parses and dispatches: each subcommand is a module with its arguments and its
//! `run`.

mod bench;
mod gpu;
mod params;
mod record;
mod recording;
mod render;
mod replay;
mod score;
mod serve;
mod simulate;
mod soak;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};
use relight_daemon::config::{self, Config};
use relight_daemon::pipeline::PipelineOptions;

#[derive(Debug, Parser)]
#[command(name = "relightd", version, about = "relight: AR relighting daemon")]
struct Cli {
    /// Configuration file.
    #[arg(long, global = true, default_value = config::DEFAULT_CONFIG_PATH)]
    config: PathBuf,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the configured pipeline as a service (the default).
    Run,
    /// Play a recording through the pipeline; prints per-stage timings at the end.
    Replay(replay::Args),
    /// Record the configured sources to an MCAP file.
    Record(record::Args),
    /// Render a scene through the simulated rig (Kinect-like depth, path-traced colour, fish-eye
    /// probe brackets, marker board, pocket lamp) into an MCAP recording with ground truth.
    /// Deterministic for a given seed.
    Simulate(simulate::Args),
    /// Replay a simulated recording with ground truth through the whole live pipeline (tracking,
    /// depth filter and merge, live mesh, lighting estimate, engine) and score every truth frame:
    /// pose, object reprojection, depth, albedo, light, composite and Δ against the truth, and
    /// the same engine on oracle inputs. Prints a table per frame and a summary.
    Score(score::Args),
    /// Replay a recording in a loop (fast, lossless) for a given time, optionally switching
    /// engines, and print the process's RSS, open descriptors and threads at intervals, with
    /// the growth after the warm-up at the end.
    Soak(soak::Args),
    /// Validate a configuration file as `run` would (the engine and its parameters, the scene,
    /// the replay file, the simulator's settings, the socket group) and print it as understood: a
    /// configuration file with every default filled in and every path resolved.
    CheckConfig,
    /// List the GPU adapters (numbered for RELIGHT_ADAPTER=#N), the one chosen, and the GPU
    /// device nodes present.
    Gpu,
    /// Check a recording, or repair one into a complete copy.
    #[command(subcommand)]
    Recording(recording::Command),
    /// Time every engine × setting × scene and measure its Δ error against the reference path
    /// tracer; prints a table, writes bench.csv, bench.json and bench.svg (speed vs error).
    Bench(bench::Args),
    /// Render an offline scene (scene.toml + glTF): writes L^ρ, L^μ, Δ and Δ's standard error as
    /// EXR, the composite and the object's pixels (the reference's) as PNG, and a summary.json
    /// with the render time.
    Render(render::Args),
}

/// Mesa's implicit Vulkan layer `VK_LAYER_MESA_device_select` connects to Wayland to order
/// devices by the display's GPU, and without a session prints "error: XDG_RUNTIME_DIR is invalid
/// or not set" once per Vulkan instance. relightd ranks adapters itself (`RELIGHT_ADAPTER`), so
/// on a machine without a display the layer is turned off with its own switch, unless the user
/// set it.
fn quiet_mesa_device_select() {
    let no_display = ["WAYLAND_DISPLAY", "DISPLAY", "XDG_RUNTIME_DIR"]
        .iter()
        .all(|v| std::env::var_os(v).is_none());
    if no_display && std::env::var_os("NODEVICE_SELECT").is_none() {
        // SAFETY: the first statement of main, before any thread exists, so nothing reads the
        // environment concurrently.
        #[allow(unsafe_code)]
        unsafe {
            std::env::set_var("NODEVICE_SELECT", "1");
        }
    }
}

/// `--engine`: a registered engine, listed in `--help` and in the error for any other name.
fn engine_name() -> clap::builder::PossibleValuesParser {
    clap::builder::PossibleValuesParser::new(relight_engines::EngineRegistry::new().names())
}

/// `render --engine`: an engine, or `reference` for the path tracer alone.
fn engine_or_reference() -> clap::builder::PossibleValuesParser {
    let mut names = vec!["reference"];
    names.extend(relight_engines::EngineRegistry::new().names());
    clap::builder::PossibleValuesParser::new(names)
}

fn main() -> std::process::ExitCode {
    quiet_mesa_device_select();
    let cli = Cli::parse();
    relight_log::init("info");
    match run(cli) {
        Ok(code) => code,
        Err(error) => {
            eprintln!("relightd: {error:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Runs the subcommand; its exit status is success unless it says otherwise (`recording check`
/// on a damaged file).
fn run(cli: Cli) -> Result<std::process::ExitCode> {
    let done = match cli.command.unwrap_or(Command::Run) {
        Command::Run => serve::run(Config::load(&cli.config)?, PipelineOptions::default(), true),
        Command::Replay(args) => replay::run(args),
        Command::Record(args) => record::run(args, &cli.config),
        Command::Simulate(args) => simulate::run(args),
        Command::Score(args) => score::run(args),
        Command::Soak(args) => soak::run(args),
        Command::CheckConfig => {
            let config = Config::load(&cli.config)?;
            // A comment line, then the configuration as understood: every default filled in,
            // every path resolved, itself a valid configuration file.
            print!("# {}: ok\n{}", cli.config.display(), config.to_toml());
            Ok(())
        }
        Command::Recording(command) => return recording::run(command),
        Command::Gpu => gpu::run(),
        Command::Bench(args) => bench::run(args),
        Command::Render(args) => render::run(args),
    };
    done.map(|()| std::process::ExitCode::SUCCESS)
}
