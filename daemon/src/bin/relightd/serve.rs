//! `relightd run` (the service) and the serving loop that `replay` shares: the pipeline, the
//! control socket, systemd's readiness and watchdog, and the summary at the end.

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use relight_daemon::config::{self, Config};
use relight_daemon::control::ControlServer;
use relight_daemon::control::types::{DeviceState, StatusReport};
use relight_daemon::pipeline::{Pipeline, PipelineOptions};

/// SIGTERM and SIGINT set the returned flag.
pub fn termination_flag() -> Result<Arc<AtomicBool>> {
    let term = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, term.clone()).context("installing signal handlers")?;
    }
    Ok(term)
}

/// Run the pipeline until a signal, or until the sources end when `exit_at_end`, serving the
/// control socket when `serve_socket`.
pub fn run(config: Config, options: PipelineOptions, serve_socket: bool) -> Result<()> {
    let term = termination_flag()?;
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
    let under_systemd = std::env::var_os("NOTIFY_SOCKET").is_some();
    let started = Instant::now();
    let mut last_ping = Instant::now();
    let mut last_status = Instant::now();
    // On a terminal, what is happening (a fast replay used to be silent until its end); hidden
    // on a pipe and under systemd, whose status line says the same.
    let spinner = indicatif::ProgressBar::new_spinner().with_style(
        indicatif::ProgressStyle::with_template("{spinner} {elapsed}  {msg}")
            .expect("a valid template"),
    );
    let mut last_shown = Instant::now();
    let done = || term.load(Ordering::Acquire) || (exit_at_end && pipeline.is_finished());
    while !done() {
        std::thread::sleep(Duration::from_millis(20));
        if !spinner.is_hidden() && last_shown.elapsed() >= Duration::from_millis(250) {
            let status = pipeline.status();
            spinner.set_message(format!(
                "{} frame sets rendered; {}",
                status.frames_rendered,
                status_line(&status)
            ));
            last_shown = Instant::now();
        }
        if under_systemd && last_status.elapsed() >= STATUS_INTERVAL {
            let line = status_line(&pipeline.status());
            notify_systemd(sd_notify::NotifyState::Status(&line));
            last_status = Instant::now();
        }
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
    spinner.finish_and_clear();
    notify_systemd(sd_notify::NotifyState::Stopping);
    let status = pipeline.status();
    pipeline.shutdown();
    if let Some(server) = server {
        server.shutdown();
    }
    print_summary(&status, started.elapsed());
    Ok(())
}

/// Whether `socket` was asked for on the command line (the default one is the service's).
pub fn is_explicit_socket(socket: &Path) -> bool {
    socket != Path::new(config::DEFAULT_SOCKET_PATH)
}

/// How often the unit's status line (`systemctl status relightd`) is refreshed.
const STATUS_INTERVAL: Duration = Duration::from_secs(5);

/// One line for systemd's `STATUS=`: engine, frame rate, latency, devices and tracking.
pub fn status_line(status: &StatusReport) -> String {
    let running = status
        .devices
        .iter()
        .filter(|d| d.state == DeviceState::Running)
        .count();
    let mut line = format!(
        "{}: {:.1} fps, latency p50 {:.0} ms, devices {running}/{} running",
        status.engine,
        status.render_fps,
        status.latency_ms.p50,
        status.devices.len()
    );
    if let Some(tracking) = &status.tracking {
        line += &format!(", tracking {}", tracking.state.name());
    }
    if status.recording.is_some() {
        line += ", recording";
    }
    line
}

/// Tell systemd (when it started us with a notify socket) how we are doing.
fn notify_systemd(state: sd_notify::NotifyState<'_>) {
    if let Err(error) = sd_notify::notify(&[state]) {
        tracing::warn!(%error, "sd_notify failed");
    }
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
    let width = status
        .stages
        .iter()
        .map(|s| s.name.chars().count())
        .max()
        .unwrap_or(0)
        .max(22);
    println!(
        "{:<width$} {:>7} {:>9} {:>9} {:>9}",
        "stage", "frames", "mean ms", "p50 ms", "p99 ms"
    );
    for stage in &status.stages {
        println!(
            "{:<width$} {:>7} {:>9.3} {:>9.3} {:>9.3}",
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
