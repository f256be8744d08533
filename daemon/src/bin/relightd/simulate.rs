//! `relightd simulate`: a scene through the simulated rig into an MCAP recording with ground
//! truth (how the demo recording is made).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::ValueEnum;
use relight_core::scene::Scene;
use relight_sim::rig::{CameraPath, SimRig, SimSettings, write_recording};

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum TrajectoryKind {
    /// The scene camera on a tripod.
    Static,
    /// The scene camera held by hand (1 cm, 0.5° tremor).
    Shake,
    /// An arc swinging ±25° around the virtual object, facing it, kept inside the room.
    Orbit,
    /// The orbit held by hand: a walk around the desk.
    Walk,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The scene directory to film.
    #[arg(long)]
    scene: PathBuf,
    /// The MCAP recording to write.
    #[arg(long)]
    out: PathBuf,
    /// Colour and depth image width.
    #[arg(long, default_value_t = 320)]
    width: u32,
    /// Colour and depth image height.
    #[arg(long, default_value_t = 240)]
    height: u32,
    /// Frames per second of depth and colour.
    #[arg(long, default_value_t = 30)]
    fps: u32,
    /// Length of the recording.
    #[arg(long, default_value_t = 3.0)]
    seconds: f64,
    /// Path-traced samples per pixel of each colour frame.
    #[arg(long, default_value_t = 16)]
    spp: u32,
    /// How the hand-held camera moves.
    #[arg(long, value_enum, default_value = "shake")]
    trajectory: TrajectoryKind,
    /// Ground truth every Nth frame (0: none).
    #[arg(long, default_value_t = 1)]
    truth_every: u32,
    /// Seeds every noise source (same seed, same recording).
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
}

pub fn run(args: Args) -> Result<()> {
    let scene = Scene::load(&args.scene)?;
    if !(args.seconds.is_finite() && args.seconds > 0.0) {
        bail!("--seconds must be positive");
    }
    let mut settings = SimSettings::placed_in(&scene);
    settings.trajectory = Some(
        match args.trajectory {
            TrajectoryKind::Static => CameraPath::Static,
            TrajectoryKind::Shake => CameraPath::Shake,
            TrajectoryKind::Orbit => CameraPath::Orbit,
            TrajectoryKind::Walk => CameraPath::Walk,
        }
        .trajectory(&scene),
    );
    settings.width = args.width;
    settings.height = args.height;
    settings.fps = args.fps;
    settings.frames = (args.seconds * f64::from(args.fps)).round().max(1.0) as u32;
    settings.color_spp = args.spp;
    settings.truth_every = args.truth_every;
    settings.seed = args.seed;
    settings.marker_corner_sigma_px = args.corner_noise_px;
    if args.no_board {
        settings.board = None;
    }
    if args.no_lamp {
        settings.lamp = None;
    }
    if args.no_probe {
        settings.probe = None;
    }
    simulate(&scene, settings, !args.no_auto_exposure, &args.out)
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
    // A bar on a terminal; on a pipe or in a log, a line every 10 frames.
    let bar = indicatif::ProgressBar::new(u64::from(frames)).with_style(
        indicatif::ProgressStyle::with_template(
            "simulating {bar:30} {pos}/{len} frames  {elapsed} (eta {eta})",
        )
        .expect("a valid template"),
    );
    let summary = write_recording(&rig, out, |i| {
        bar.set_position(u64::from(i + 1));
        if bar.is_hidden() && ((i + 1) % 10 == 0 || i + 1 == frames) {
            eprintln!(
                "simulated {}/{frames} frames ({:.1} s)",
                i + 1,
                started.elapsed().as_secs_f64()
            );
        }
    })
    .with_context(|| format!("simulating into {}", out.display()))?;
    bar.finish_and_clear();
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
