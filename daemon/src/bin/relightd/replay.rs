//! `relightd replay`: a recording through the pipeline without a configuration file (the demo),
//! or with the live settings of one (`--live-config`).

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Result;
use clap::ValueEnum;
use relight_core::StreamKind;
use relight_daemon::config::{self, Config, OutputConfig, ReplayConfig, SourceConfig};
use relight_daemon::pipeline::PipelineOptions;
use relight_daemon::pipeline::tracking::TrackingSource;

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Mode {
    Realtime,
    Fast,
    Stepped,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The MCAP recording to play.
    recording: PathBuf,
    /// `realtime` at the recorded pace, `fast` as fast as the pipeline takes it, `stepped`
    /// one frame set per `relightctl step`.
    #[arg(long, value_enum, default_value = "realtime")]
    mode: Mode,
    /// Playback speed for `realtime` mode.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Start over at the end (runs until stopped).
    #[arg(long = "loop")]
    looping: bool,
    /// The engine to start with.
    #[arg(long, default_value = "passthrough", value_parser = crate::engine_name())]
    engine: String,
    /// Its parameters (`name=value`, repeatable), as `relightctl engine params set`.
    #[arg(long = "param")]
    params: Vec<String>,
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
    /// Serve the live view to Foxglove on this address (`127.0.0.1:8765`; port 0 picks one,
    /// which `relightctl status` shows): open it in Foxglove as a WebSocket connection.
    #[arg(long, value_name = "ADDR")]
    live_view: Option<SocketAddr>,
    /// Serve the read-only browser page on this address (`127.0.0.1:8766`).
    #[arg(long, value_name = "ADDR")]
    live_page: Option<SocketAddr>,
    /// Where the camera pose comes from, as `[tracking] source` (default: the markers when the
    /// recording's calibration knows a board, else the scene's camera).
    #[arg(long, value_enum)]
    tracking: Option<TrackingSource>,
    /// Read a stream from another topic, for a bag another tool recorded (repeatable):
    /// `--topic color=/camera/color/image_raw --topic depth=/camera/depth/image_rect_raw`.
    #[arg(long = "topic", value_name = "STREAM=TOPIC", value_parser = stream_topic)]
    topics: Vec<(StreamKind, String)>,
    /// Take `[scene]`, `[tracking]` and `[sync]` from this configuration file, as `relightd
    /// score --live-config` does (default: the built-in defaults), to try live settings such as
    /// `[scene] depth_stride` on a recording; `--scene` and `--tracking` override the file's.
    #[arg(long = "live-config")]
    live_config: Option<PathBuf>,
}

fn stream_topic(text: &str) -> Result<(StreamKind, String), String> {
    let (stream, topic) = text
        .split_once('=')
        .ok_or_else(|| format!("`{text}` is not STREAM=TOPIC"))?;
    let kind = StreamKind::from_name(stream).ok_or_else(|| {
        format!(
            "`{stream}` is not a stream; the streams are {}",
            config::stream_names()
        )
    })?;
    if topic.is_empty() {
        return Err(format!("`{text}` names no topic"));
    }
    Ok((kind, topic.to_owned()))
}

pub fn run(args: Args) -> Result<()> {
    let live = match &args.live_config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let mut config = Config {
        path: PathBuf::from("(command line)"),
        source: SourceConfig::Replay(ReplayConfig {
            path: args.recording,
            mode: match args.mode {
                Mode::Realtime => config::ReplayMode::Realtime,
                Mode::Fast => config::ReplayMode::Fast,
                Mode::Stepped => config::ReplayMode::Stepped,
            },
            loop_playback: args.looping,
            speed: args.speed,
            topics: args.topics.into_iter().collect(),
        }),
        output: OutputConfig {
            dir: args.output,
            every_n: args.every_n,
        },
        sync: live.sync,
        scene: live.scene,
        tracking: live.tracking,
        ..Config::default()
    };
    config.engine.name = args.engine;
    config.engine.params = serde_json::Value::Object(crate::params::parse_params(&args.params)?);
    if args.scene.is_some() {
        config.scene.dir = args.scene;
    }
    if args.tracking.is_some() {
        config.tracking.source = args.tracking;
    }
    config.live_view.foxglove = args.live_view;
    config.live_view.page = args.live_page;
    if let Some(socket) = args.socket {
        config.daemon.socket = socket;
    }
    let serve_socket = crate::serve::is_explicit_socket(&config.daemon.socket);
    let options = PipelineOptions {
        exit_at_end: !args.looping,
        ..PipelineOptions::default()
    };
    crate::serve::run(config, options, serve_socket)
}
