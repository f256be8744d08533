//! relightd: the relight service.
//!
//! `relightd [--config FILE]` runs the configured pipeline as a service (systemd Type=notify);
//! `relightd replay FILE` plays a recording through the pipeline without a configuration file
//! (the demo); `relightd record` captures the configured sources to an MCAP file;
//! `relightd simulate` renders a scene through the simulated rig into a recording with ground
//! truth (how the demo recording is made); `relightd render` renders an offline scene with an
//! engine; `relightd check-config` validates a configuration file.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use relight_backends::sim::rig::{CameraPath, SimRig, SimSettings, write_recording};
use relight_core::scene::Scene;
use relight_daemon::bench;
use relight_daemon::config::{self, Config, OutputConfig, ReplayConfig, SourceConfig};
use relight_daemon::control::ControlServer;
use relight_daemon::control::types::StatusReport;
use relight_daemon::pipeline::{Pipeline, PipelineOptions};
use relight_daemon::sinks::exr_out::write_exr;
use relight_daemon::sinks::png_out::{tonemap_reinhard, write_png};
use relight_reference::{ReferenceSettings, render_reference};

#[derive(Debug, Parser)]
#[command(name = "relightd", version, about = "relight: AR relighting daemon")]
struct Cli {
    /// Configuration file.
    #[arg(long, global = true, default_value = config::DEFAULT_CONFIG_PATH)]
    config: PathBuf,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Mode {
    Realtime,
    Fast,
    Stepped,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum TrajectoryKind {
    /// The scene camera on a tripod.
    Static,
    /// The scene camera held by hand (1 cm, 0.5° tremor).
    Shake,
    /// An arc swinging ±25° around the virtual object, facing it, kept inside the room.
    Orbit,
    /// The orbit held by hand: a walk around the desk.
    Walk,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the configured pipeline as a service (the default).
    Run,
    /// Play a recording through the pipeline; prints per-stage timings at the end.
    Replay {
        recording: PathBuf,
        #[arg(long, value_enum, default_value = "realtime")]
        mode: Mode,
        /// Playback speed for `realtime` mode.
        #[arg(long, default_value_t = 1.0)]
        speed: f64,
        /// Start over at the end (runs until stopped).
        #[arg(long = "loop")]
        looping: bool,
        #[arg(long, default_value = "passthrough")]
        engine: String,
        /// Write composite PNGs here.
        #[arg(long)]
        output: Option<PathBuf>,
        /// Write every Nth frame to --output.
        #[arg(long, default_value_t = 1)]
        every_n: u32,
        /// Serve the control socket here while replaying.
        #[arg(long)]
        socket: Option<PathBuf>,
        /// Scene directory for the GPU engines: virtual object(s), lights, camera pose (the
        /// real surface comes from the recording's depth).
        #[arg(long)]
        scene: Option<PathBuf>,
    },
    /// Record the configured sources to an MCAP file.
    Record {
        #[arg(long)]
        out: PathBuf,
        /// Stop after this many seconds (default: until SIGINT/SIGTERM or the sources end).
        #[arg(long)]
        seconds: Option<f64>,
    },
    /// Render a scene through the simulated rig (Kinect-like depth, path-traced colour, fish-eye
    /// probe brackets, marker board, pocket lamp) into an MCAP recording with ground truth.
    /// Deterministic for a given seed.
    Simulate {
        #[arg(long)]
        scene: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 320)]
        width: u32,
        #[arg(long, default_value_t = 240)]
        height: u32,
        #[arg(long, default_value_t = 30)]
        fps: u32,
        #[arg(long, default_value_t = 3.0)]
        seconds: f64,
        /// Path-traced samples per pixel of each colour frame.
        #[arg(long, default_value_t = 16)]
        spp: u32,
        #[arg(long, value_enum, default_value = "shake")]
        trajectory: TrajectoryKind,
        /// Ground truth every Nth frame (0: none).
        #[arg(long, default_value_t = 1)]
        truth_every: u32,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Gaussian noise on each detected tag corner, pixels (0: ideal). The default is what
        /// the AprilTag backend's edge-refined corners reach on sharp images.
        #[arg(long, default_value_t = 0.1)]
        corner_noise_px: f32,
        /// Leave out the marker board.
        #[arg(long)]
        no_board: bool,
        /// Leave out the pocket lamp.
        #[arg(long)]
        no_lamp: bool,
        /// Leave out the fish-eye probe.
        #[arg(long)]
        no_probe: bool,
        /// Keep the fixed exposures (colour 1.0, probe scale 1.0) instead of metering them on
        /// the first frame.
        #[arg(long)]
        no_auto_exposure: bool,
    },
    /// Replay a simulated recording with ground truth through the whole live pipeline (tracking,
    /// depth filter and merge, live mesh, lighting estimate, engine) and score every truth frame:
    /// pose, object reprojection, depth, albedo, light, composite and Δ against the truth, and
    /// the same engine on oracle inputs. Prints a table per frame and a summary.
    Score {
        recording: PathBuf,
        #[arg(long)]
        scene: PathBuf,
        #[arg(long, default_value = "differential")]
        engine: String,
        /// Engine parameters (`name=value`, repeatable).
        #[arg(long = "param")]
        params: Vec<String>,
        /// Samples per pixel of the truth's reference renders.
        #[arg(long, default_value_t = 32)]
        reference_spp: u32,
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
    },
    /// Replay a recording in a loop (fast, lossless) for a given time, optionally switching
    /// engines, and print the process's RSS, open descriptors and threads at intervals, with
    /// the growth after the warm-up at the end.
    Soak {
        recording: PathBuf,
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Engines to run; with --switch-every, each in turn (repeatable or comma-separated).
        #[arg(long = "engine", value_delimiter = ',', default_value = "differential")]
        engines: Vec<String>,
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
    },
    /// Validate a configuration file and print it as understood.
    CheckConfig,
    /// Time every engine × setting × scene and measure its Δ error against the reference path
    /// tracer; prints a table, writes bench.csv, bench.json and bench.svg (speed vs error).
    Bench {
        /// Scene directories (default: every scene under tests/scenes).
        #[arg(long = "scene")]
        scenes: Vec<PathBuf>,
        #[arg(long, default_value_t = 160)]
        width: u32,
        #[arg(long, default_value_t = 120)]
        height: u32,
        /// Reference samples per pixel.
        #[arg(long, default_value_t = 256)]
        reference_spp: u32,
        /// Timed frames per case (after two warm-up frames); the median is reported.
        #[arg(long, default_value_t = 5)]
        frames: u32,
        /// Add the papers' parameter sweeps (DLPV volume × steps and RSM sizes, DVCT volume × step, DIR VPL count and ISM size, IBL map size).
        #[arg(long)]
        sweep: bool,
        /// Only these engines.
        #[arg(long = "engine")]
        engines: Vec<String>,
        /// Instead of the engine table: time the `ibl` map convolution (diffuse + 8 specular
        /// maps in one pass) at these output sizes, e.g. `--ibl-maps 128,256,512`.
        #[arg(long, value_delimiter = ',')]
        ibl_maps: Vec<u32>,
        #[arg(long, default_value = "target/bench")]
        out: PathBuf,
    },
    /// Render an offline scene (scene.toml + glTF): writes L^ρ, L^μ, Δ and Δ's standard error as
    /// EXR, the composite as PNG, and a summary.json with the render time.
    Render {
        #[arg(long)]
        scene: PathBuf,
        #[arg(long, default_value = "reference")]
        engine: String,
        /// Reference samples per pixel (for another engine: of the reference it is judged
        /// against, whose L^μ is also its camera image).
        #[arg(long, default_value_t = 64)]
        spp: u32,
        #[arg(long)]
        out: PathBuf,
        /// Override the scene camera's image size.
        #[arg(long, requires = "height")]
        width: Option<u32>,
        #[arg(long, requires = "width")]
        height: Option<u32>,
        /// Bounces after the first hit.
        #[arg(long, default_value_t = 8)]
        bounces: u32,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Engine parameters (`name=value`, repeatable), as `relightctl engine params set`.
        #[arg(long = "param")]
        params: Vec<String>,
    },
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("RELIGHT_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("relightd: {error:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command.unwrap_or(Command::Run) {
        Command::Run => {
            let config = Config::load(&cli.config)?;
            serve(config, PipelineOptions::default(), true)
        }
        Command::Bench {
            scenes,
            width,
            height,
            reference_spp,
            frames,
            sweep,
            engines,
            ibl_maps,
            out,
        } => {
            if !ibl_maps.is_empty() {
                println!("size     input texels  maps  median ms");
                for row in bench::ibl_map_timings(&ibl_maps, 8, frames)? {
                    println!(
                        "{:>4}²  {:>13}  {:>4}  {:>9.1}",
                        row.size,
                        row.input_texels,
                        row.levels + 1,
                        row.median_ms
                    );
                }
                return Ok(());
            }
            let scenes = if scenes.is_empty() {
                let mut found: Vec<PathBuf> = std::fs::read_dir("tests/scenes")
                    .context("no --scene given and no tests/scenes here")?
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.join("scene.toml").exists())
                    .collect();
                found.sort();
                found
            } else {
                scenes
            };
            let cases = bench::default_cases(sweep)
                .into_iter()
                .filter(|c| engines.is_empty() || engines.contains(&c.engine))
                .collect();
            let settings = bench::BenchSettings {
                scenes,
                width,
                height,
                reference_spp,
                frames,
                cases,
            };
            let adapter = relight_engines::gpu::GpuContext::new()
                .map(|c| format!("{} ({:?})", c.info.name, c.info.backend))
                .unwrap_or_else(|e| format!("no GPU: {e}"));
            eprintln!("bench on {adapter}");
            let rows = bench::run(&settings, |row| {
                eprintln!(
                    "{:<14} {:<52} {:>9.2} ms  rel L2 {:.4}",
                    row.scene, row.setting, row.median_ms, row.relative_l2
                );
            })?;
            print!("{}", bench::table(&rows));
            bench::write_outputs(&rows, &out, &adapter)?;
            println!("wrote {}/bench.{{csv,json,svg}}", out.display());
            Ok(())
        }
        Command::Score {
            recording,
            scene,
            engine,
            params,
            reference_spp,
            out,
            json,
            live_config,
            summary,
        } => {
            let config = match live_config {
                Some(path) => Config::load(&path)?,
                None => relight_daemon::score::default_config(),
            };
            let settings = relight_daemon::score::ScoreSettings {
                recording,
                scene,
                engine,
                params: parse_params(&params)?,
                reference_spp,
                out,
                config,
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
            match (summary, table.find("\n\n")) {
                (true, Some(end)) => print!("{}", &table[end + 2..]),
                _ => print!("{table}"),
            }
            if let Some(path) = json {
                std::fs::write(&path, serde_json::to_string_pretty(&report.to_json())?)
                    .with_context(|| format!("writing {}", path.display()))?;
                println!("wrote {}", path.display());
            }
            Ok(())
        }
        Command::Soak {
            recording,
            scene,
            engines,
            seconds,
            switch_every,
            sample_every,
            warmup,
            json,
            live_config,
        } => {
            let positive = |name: &str, v: f64| {
                if v.is_finite() && v > 0.0 {
                    Ok(Duration::from_secs_f64(v))
                } else {
                    Err(anyhow::anyhow!(
                        "--{name} must be a positive number of seconds"
                    ))
                }
            };
            let settings = relight_daemon::soak::SoakSettings {
                recording,
                scene,
                engines,
                duration: positive("seconds", seconds)?,
                switch_every: switch_every
                    .map(|s| positive("switch-every", s))
                    .transpose()?,
                sample_every: positive("sample-every", sample_every)?,
                warmup: Duration::from_secs_f64(warmup.max(0.0)),
                config: match live_config {
                    Some(path) => Config::load(&path)?,
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
            if let Some(path) = json {
                relight_daemon::soak::write_json(&report, &path)?;
                println!("wrote {}", path.display());
            }
            Ok(())
        }
        Command::CheckConfig => {
            let config = Config::load(&cli.config)?;
            println!("{}: ok\n{config:#?}", cli.config.display());
            Ok(())
        }
        Command::Replay {
            recording,
            mode,
            speed,
            looping,
            engine,
            output,
            every_n,
            socket,
            scene,
        } => {
            let mut config = Config {
                path: PathBuf::from("(command line)"),
                source: SourceConfig::Replay(ReplayConfig {
                    path: recording,
                    mode: match mode {
                        Mode::Realtime => config::ReplayMode::Realtime,
                        Mode::Fast => config::ReplayMode::Fast,
                        Mode::Stepped => config::ReplayMode::Stepped,
                    },
                    loop_playback: looping,
                    speed,
                }),
                output: OutputConfig {
                    dir: output,
                    every_n,
                },
                ..Config::default()
            };
            config.engine.name = engine;
            config.scene.dir = scene;
            if let Some(socket) = socket {
                config.daemon.socket = socket;
            }
            let serve_socket = config.daemon.socket != Path::new(config::DEFAULT_SOCKET_PATH);
            let options = PipelineOptions {
                exit_at_end: !looping,
                ..PipelineOptions::default()
            };
            serve(config, options, serve_socket)
        }
        Command::Record { out, seconds } => {
            let mut config = Config::load(&cli.config)?;
            config.recorder.autostart = false;
            record(config, &out, seconds.map(Duration::from_secs_f64))
        }
        Command::Simulate {
            scene,
            out,
            width,
            height,
            fps,
            seconds,
            spp,
            trajectory,
            truth_every,
            seed,
            corner_noise_px,
            no_board,
            no_lamp,
            no_probe,
            no_auto_exposure,
        } => {
            let scene = Scene::load(&scene)?;
            if !(seconds.is_finite() && seconds > 0.0) {
                bail!("--seconds must be positive");
            }
            let mut settings = SimSettings::placed_in(&scene);
            settings.trajectory = Some(
                match trajectory {
                    TrajectoryKind::Static => CameraPath::Static,
                    TrajectoryKind::Shake => CameraPath::Shake,
                    TrajectoryKind::Orbit => CameraPath::Orbit,
                    TrajectoryKind::Walk => CameraPath::Walk,
                }
                .trajectory(&scene),
            );
            settings.width = width;
            settings.height = height;
            settings.fps = fps;
            settings.frames = (seconds * f64::from(fps)).round().max(1.0) as u32;
            settings.color_spp = spp;
            settings.truth_every = truth_every;
            settings.seed = seed;
            settings.marker_corner_sigma_px = corner_noise_px;
            if no_board {
                settings.board = None;
            }
            if no_lamp {
                settings.lamp = None;
            }
            if no_probe {
                settings.probe = None;
            }
            simulate(&scene, settings, !no_auto_exposure, &out)
        }
        Command::Render {
            scene,
            engine,
            spp,
            out,
            width,
            height,
            bounces,
            seed,
            params,
        } => {
            if engine != "reference" {
                return render_engine(&scene, &engine, &params, width.zip(height), spp, &out);
            }
            let settings = ReferenceSettings {
                spp,
                max_bounces: bounces,
                seed,
                size: width.zip(height),
                ..ReferenceSettings::default()
            };
            render(&scene, settings, &out)
        }
    }
}

/// Run the pipeline until a signal, or until the sources end when `exit_at_end`, serving the
/// control socket when `serve_socket`.
fn serve(config: Config, options: PipelineOptions, serve_socket: bool) -> Result<()> {
    let term = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, term.clone()).context("installing signal handlers")?;
    }
    let daemon = config.daemon.clone();
    let allowed_gid = daemon
        .socket_group
        .as_ref()
        .map(config::GroupSpec::resolve_gid)
        .transpose()
        .context("[daemon] socket_group")?;
    let exit_at_end = options.exit_at_end;
    let mut pipeline = Pipeline::start(config, options)?;
    let server = match serve_socket {
        false => None,
        true => {
            if let Some(dir) = daemon.socket.parent() {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
            }
            let server = ControlServer::bind(
                &daemon.socket,
                daemon.socket_mode,
                allowed_gid,
                daemon.max_request_bytes,
                pipeline.control(),
            )?;
            tracing::info!(socket = %daemon.socket.display(), "control socket ready");
            Some(server.spawn().context("starting the control server")?)
        }
    };
    let watchdog = daemon.watchdog.then(sd_notify::watchdog_enabled).flatten();
    notify_systemd(sd_notify::NotifyState::Ready);
    let started = Instant::now();
    let mut last_ping = Instant::now();
    let done = || term.load(Ordering::Acquire) || (exit_at_end && pipeline.is_finished());
    while !done() {
        std::thread::sleep(Duration::from_millis(20));
        if let Some(interval) = watchdog
            && last_ping.elapsed() >= interval / 2
        {
            // Ping only while the render loop is alive: a hung pipeline gets restarted.
            if pipeline.is_healthy(interval / 2) {
                notify_systemd(sd_notify::NotifyState::Watchdog);
            } else {
                tracing::error!("render loop stalled; withholding the watchdog ping");
            }
            last_ping = Instant::now();
        }
    }
    notify_systemd(sd_notify::NotifyState::Stopping);
    let status = pipeline.status();
    pipeline.shutdown();
    if let Some(server) = server {
        server.shutdown();
    }
    print_summary(&status, started.elapsed());
    Ok(())
}

/// Tell systemd (when it started us with a notify socket) how we are doing.
fn notify_systemd(state: sd_notify::NotifyState<'_>) {
    if let Err(error) = sd_notify::notify(&[state]) {
        tracing::warn!(%error, "sd_notify failed");
    }
}

fn record(config: Config, out: &Path, seconds: Option<Duration>) -> Result<()> {
    let term = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, term.clone()).context("installing signal handlers")?;
    }
    let options = PipelineOptions {
        exit_at_end: true,
        ..PipelineOptions::default()
    };
    let mut pipeline = Pipeline::start(config, options)?;
    let control = pipeline.control();
    control
        .record_start(Some(out.to_path_buf()))
        .map_err(|e| anyhow::anyhow!("{}", e.message))?;
    let started = Instant::now();
    while !term.load(Ordering::Acquire)
        && !pipeline.is_finished()
        && seconds.is_none_or(|s| started.elapsed() < s)
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

fn simulate(scene: &Scene, settings: SimSettings, auto_exposure: bool, out: &Path) -> Result<()> {
    let frames = settings.frames;
    let mut rig = SimRig::new(scene, settings)?;
    if auto_exposure {
        rig = rig.metered();
        let probe_scale = rig.settings().probe.as_ref().map(|p| p.exposure_scale);
        eprintln!(
            "metered exposure: colour {:.4}, probe scale {probe_scale:?}",
            rig.settings().exposure
        );
    }
    let started = Instant::now();
    let summary = write_recording(&rig, out, |i| {
        if (i + 1) % 10 == 0 || i + 1 == frames {
            eprintln!(
                "simulated {}/{frames} frames ({:.1} s)",
                i + 1,
                started.elapsed().as_secs_f64()
            );
        }
    })
    .with_context(|| format!("simulating into {}", out.display()))?;
    let bytes = std::fs::metadata(out).map(|m| m.len()).unwrap_or(0);
    println!(
        "{}: {} messages ({:?}), {frames} frames of {}×{}, {bytes} bytes, {:.1} s",
        out.display(),
        summary.total_messages(),
        summary.messages,
        rig.settings().width,
        rig.settings().height,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

fn render(scene_dir: &Path, settings: ReferenceSettings, out: &Path) -> Result<()> {
    let scene = Scene::load(scene_dir)?;
    let started = Instant::now();
    let images = render_reference(&scene, settings)?;
    let seconds = started.elapsed().as_secs_f64();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let (w, h) = (images.width, images.height);
    for (name, pixels) in [
        ("l_rho", &images.l_rho),
        ("l_mu", &images.l_mu),
        ("delta", &images.delta),
        ("delta_std_error", &images.delta_std_error),
    ] {
        write_exr(&out.join(format!("{name}.exr")), w, h, pixels)?;
    }
    // Offline, the background is L^μ itself, so background + Δ on real pixels and L^ρ on
    // virtual pixels are both L^ρ.
    write_png(
        &out.join("composite.png"),
        &tonemap_reinhard(w, h, &images.l_rho),
    )?;
    let real = images.virtual_mask.iter().filter(|v| !**v).count().max(1);
    let mean_std_error = images
        .delta_std_error
        .iter()
        .zip(&images.virtual_mask)
        .filter(|(_, v)| !**v)
        .map(|(e, _)| f64::from(e.max_element()))
        .sum::<f64>()
        / real as f64;
    let summary = serde_json::json!({
        "scene": scene.name,
        "engine": "reference",
        "width": w,
        "height": h,
        "spp": images.spp,
        "max_bounces": settings.max_bounces,
        "seconds": seconds,
        "mean_delta_std_error_real_pixels": mean_std_error,
    });
    std::fs::write(
        out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    println!(
        "{}: {w}×{h}, {} spp in {seconds:.2} s; mean std error of Δ on real pixels {mean_std_error:.2e}; wrote {}",
        scene.name,
        images.spp,
        out.display()
    );
    Ok(())
}

/// Render an offline scene with a relighting engine: Δ as EXR, the composite as PNG, and a
/// summary with the frame time and the error of Δ against the reference at `spp`.
fn render_engine(
    scene_dir: &Path,
    engine: &str,
    params: &[String],
    size: Option<(u32, u32)>,
    spp: u32,
    out: &Path,
) -> Result<()> {
    let scene = Arc::new(Scene::load(scene_dir)?);
    let (w, h) = size.unwrap_or((scene.camera.width, scene.camera.height));
    let mut built = relight_engines::EngineRegistry::new().build(engine, &parse_params(params)?)?;
    let reference = relight_engines::offline::reference(&scene, w, h, spp)?;
    let frame = relight_engines::offline::scene_frame(
        scene.clone(),
        relight_engines::offline::background(&reference),
    );
    let mut relit = relight_engines::RelitFrame::default();
    built.engine.render(&frame, &mut relit)?;
    let started = Instant::now();
    built.engine.render(&frame, &mut relit)?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    let delta = relight_engines::offline::delta_pixels(&relit.delta);
    let (relative_l2, max_abs) =
        relight_engines::offline::delta_error(&delta, &reference.delta, &reference.virtual_mask);
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_exr(&out.join("delta.exr"), w, h, &delta)?;
    write_exr(&out.join("delta_reference.exr"), w, h, &reference.delta)?;
    write_png(&out.join("composite.png"), &relit.composite)?;
    let summary = serde_json::json!({
        "scene": scene.name,
        "engine": engine,
        "params": built.params,
        "width": w,
        "height": h,
        "frame_ms": ms,
        "passes": relit.timings.iter().map(|t| serde_json::json!({"pass": t.pass, "ms": t.ms})).collect::<Vec<_>>(),
        "reference_spp": spp,
        "delta_relative_l2": relative_l2,
        "delta_max_abs": max_abs,
    });
    std::fs::write(
        out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    println!(
        "{}: {engine} {w}×{h} in {ms:.1} ms; Δ vs reference ({spp} spp): relative L2 {relative_l2:.4}, max abs {max_abs:.4}; wrote {}",
        scene.name,
        out.display()
    );
    Ok(())
}

/// `--param name=value` arguments as engine parameters (values as JSON where they parse).
fn parse_params(params: &[String]) -> Result<serde_json::Map<String, serde_json::Value>> {
    let mut map = serde_json::Map::new();
    for param in params {
        let (key, value) = param
            .split_once('=')
            .with_context(|| format!("--param `{param}`: expected name=value"))?;
        let value = serde_json::from_str(value).unwrap_or_else(|_| serde_json::Value::from(value));
        map.insert(key.to_owned(), value);
    }
    Ok(map)
}

fn print_summary(status: &StatusReport, elapsed: Duration) {
    let skipped = &status.frames_skipped;
    println!(
        "rendered {} of {} frame sets in {:.2} s ({} with a missing stream), engine {} ({} not rendered)",
        status.frames_rendered,
        status.reference_frames,
        elapsed.as_secs_f64(),
        status.sync_missing,
        status.engine,
        status.render_errors,
    );
    println!(
        "skipped {} (superseded {}, discarded by the synchroniser {}, queue drops {}); latency p50 {:.1} ms p99 {:.1} ms; outputs dropped {} failed {}",
        skipped.total,
        skipped.superseded,
        skipped.sync_discarded,
        skipped.queue_dropped,
        status.latency_ms.p50,
        status.latency_ms.p99,
        status.outputs_dropped,
        status.outputs_failed,
    );
    println!(
        "{:<22} {:>7} {:>9} {:>9} {:>9}",
        "stage", "frames", "mean ms", "p50 ms", "p99 ms"
    );
    for stage in &status.stages {
        println!(
            "{:<22} {:>7} {:>9.3} {:>9.3} {:>9.3}",
            stage.name, stage.frames, stage.mean_ms, stage.p50_ms, stage.p99_ms
        );
    }
    for s in &status.sync_streams {
        println!(
            "sync   {:<8} matched {:>5} missing {:>5} late {:>4} dropped {:>4}",
            s.stream.name(),
            s.matched,
            s.missing,
            s.late,
            s.dropped
        );
    }
    for device in &status.devices {
        println!(
            "device {:<8} {:<8} {:<9} frames {:>6} drops {:>4}{}",
            device.name,
            device.stream.name(),
            device.state.name(),
            device.frames,
            device.drops,
            device
                .last_error
                .as_ref()
                .map(|e| format!("  last error: {e}"))
                .unwrap_or_default()
        );
    }
}
