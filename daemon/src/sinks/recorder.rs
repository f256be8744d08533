//! The MCAP recorder: a thread with its own bus subscription (every message of every stream,
//! bounded queue, drop-oldest so a slow disk never stalls capture) that writes while recording.
//! When asked to (`[recorder] outputs`), the render thread also offers it each frame's
//! composite, Δ and lighting estimate through a short queue; an offer it cannot take at once is
//! dropped and counted, so the recorder never holds up a frame.
//!
//! The file is opened on that thread, as a regular file only ([`super::safe_file`]: a FIFO or a
//! link is refused at once, and an existing file unless the request replaces it). A request waits for the thread at most [`ANSWER_TIMEOUT`]: a
//! recorder stuck on its disk answers "busy" instead of holding the control connection.

use std::fs::File;
use std::io::BufWriter;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender, TrySendError, bounded};
use relight_core::StreamMessage;
use relight_core::bus::{Bus, Subscription};
use relight_core::recording::RecordingError;
use relight_core::recording::{OutputMessage, RecordingMeta, RecordingOptions, RecordingWriter};
use serde_json::{Value, json};

use super::safe_file::Existing;

/// How long a request waits for the recorder thread's answer.
pub const ANSWER_TIMEOUT: Duration = Duration::from_secs(3);

/// Output messages (three per frame) queued before offers are dropped.
const OUTPUT_QUEUE: usize = 12;

/// How a recording is written: the writer's options, and whether the render thread's outputs
/// go in beside the streams.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RecordSettings {
    pub options: RecordingOptions,
    pub outputs: bool,
}

enum Command {
    Start {
        path: PathBuf,
        existing: Existing,
        settings: RecordSettings,
        reply: Sender<Result<PathBuf, RecorderError>>,
    },
    Stop {
        reply: Sender<Result<Value, RecorderError>>,
    },
}

/// Why a recorder request did not do what it asked.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RecorderError {
    /// Another request is in the way (already recording, or the thread is stuck on its disk):
    /// try again later.
    #[error("{0}")]
    Busy(String),
    #[error("{0}")]
    Failed(String),
    /// The file could not be created: the message names it and says why.
    #[error("cannot start recording: {message}")]
    File { path: PathBuf, message: String },
}

/// What the status report shows of the recorder.
#[derive(Debug, Default)]
pub struct RecorderStatus {
    active: AtomicBool,
    /// Whether the active recording takes the render thread's outputs.
    outputs: AtomicBool,
    messages: AtomicU64,
    outputs_dropped: AtomicU64,
    path: Mutex<Option<PathBuf>>,
}

impl RecorderStatus {
    /// The file being written and the messages written so far, while recording.
    pub fn current(&self) -> Option<(PathBuf, u64)> {
        if !self.active.load(Ordering::Acquire) {
            return None;
        }
        let path = self
            .path
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()?;
        Some((path, self.messages.load(Ordering::Relaxed)))
    }
}

/// Handle to the recorder thread.
#[derive(Debug)]
pub struct Recorder {
    commands: Sender<Command>,
    outputs: Sender<OutputMessage>,
    status: Arc<RecorderStatus>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Command {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Command::Start { path, .. } => write!(f, "Start({})", path.display()),
            Command::Stop { .. } => f.write_str("Stop"),
        }
    }
}

impl Recorder {
    /// Subscribe to `bus` with a queue of `queue_frames` messages and start the thread.
    /// `meta` (calibration, source) is embedded in every file written.
    pub fn spawn(bus: &Bus, queue_frames: usize, meta: RecordingMeta) -> std::io::Result<Self> {
        let subscription = bus.all.subscribe_named("recorder", queue_frames.max(1));
        let (commands, rx) = bounded(4);
        let (outputs, output_rx) = bounded(OUTPUT_QUEUE);
        let status = Arc::new(RecorderStatus::default());
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let status = status.clone();
            let stop = stop.clone();
            std::thread::Builder::new()
                .name("recorder".into())
                .spawn(move || run(&subscription, &rx, &output_rx, &status, &stop, &meta))?
        };
        Ok(Self {
            commands,
            outputs,
            status,
            stop,
            thread: Some(thread),
        })
    }

    pub fn status(&self) -> &Arc<RecorderStatus> {
        &self.status
    }

    pub fn start(
        &self,
        path: PathBuf,
        existing: Existing,
        settings: RecordSettings,
    ) -> Result<PathBuf, RecorderError> {
        let (reply, answer) = bounded(1);
        self.send(
            Command::Start {
                path,
                existing,
                settings,
                reply,
            },
            &answer,
        )
    }

    /// Whether a recording is taking the render thread's outputs now.
    pub fn wants_outputs(&self) -> bool {
        self.status.active.load(Ordering::Acquire) && self.status.outputs.load(Ordering::Acquire)
    }

    /// Offer one output message; dropped (and counted) when the queue is full. Never blocks.
    pub fn offer_output(&self, output: OutputMessage) {
        if self.outputs.try_send(output).is_err() {
            self.status.outputs_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    pub fn stop_recording(&self) -> Result<Value, RecorderError> {
        let (reply, answer) = bounded(1);
        self.send(Command::Stop { reply }, &answer)
    }

    fn send<T>(
        &self,
        command: Command,
        answer: &Receiver<Result<T, RecorderError>>,
    ) -> Result<T, RecorderError> {
        let stuck = || {
            RecorderError::Busy(format!(
                "the recorder has not answered for {} s (its disk may be stuck); try again later",
                ANSWER_TIMEOUT.as_secs()
            ))
        };
        self.commands.try_send(command).map_err(|e| match e {
            TrySendError::Full(_) => stuck(),
            TrySendError::Disconnected(_) => {
                RecorderError::Failed("the recorder thread has ended".to_owned())
            }
        })?;
        answer.recv_timeout(ANSWER_TIMEOUT).map_err(|_| stuck())?
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        if self.status.current().is_some()
            && let Err(error) = self.stop_recording()
        {
            tracing::error!(%error, "recording not finished cleanly");
        }
        self.stop.store(true, Ordering::Release);
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            tracing::error!("recorder thread panicked");
        }
    }
}

struct Active {
    path: PathBuf,
    writer: RecordingWriter<BufWriter<File>>,
    drops_at_start: u64,
    output_drops_at_start: u64,
}

impl Active {
    /// Write one message; on failure the recording ends (logged) and `false` comes back.
    fn record_outcome(&self, status: &RecorderStatus, what: Result<(), RecordingError>) -> bool {
        match what {
            Ok(()) => {
                status.messages.fetch_add(1, Ordering::Relaxed);
                true
            }
            Err(error) => {
                tracing::error!(path = %self.path.display(), %error, "recording stopped: write failed");
                status.active.store(false, Ordering::Release);
                false
            }
        }
    }
}

fn run(
    subscription: &Subscription<StreamMessage>,
    commands: &Receiver<Command>,
    outputs: &Receiver<OutputMessage>,
    status: &RecorderStatus,
    stop: &AtomicBool,
    meta: &RecordingMeta,
) {
    let mut active: Option<Active> = None;
    while !stop.load(Ordering::Acquire) {
        while let Ok(command) = commands.try_recv() {
            match command {
                Command::Start {
                    path,
                    existing,
                    settings,
                    reply,
                } => {
                    let result = if active.is_some() {
                        Err(RecorderError::Busy(
                            "already recording; stop first".to_owned(),
                        ))
                    } else {
                        match create(&path, existing, meta, &settings.options) {
                            Err(message) => Err(RecorderError::File { path, message }),
                            Ok(writer) => {
                                // Discard what queued up before the start.
                                while subscription.try_recv().is_some() {}
                                while outputs.try_recv().is_ok() {}
                                *status.path.lock().unwrap_or_else(PoisonError::into_inner) =
                                    Some(path.clone());
                                status.messages.store(0, Ordering::Relaxed);
                                status.outputs.store(settings.outputs, Ordering::Release);
                                status.active.store(true, Ordering::Release);
                                tracing::info!(path = %path.display(), outputs = settings.outputs, "recording started");
                                active = Some(Active {
                                    path: path.clone(),
                                    writer,
                                    drops_at_start: subscription.dropped(),
                                    output_drops_at_start: status
                                        .outputs_dropped
                                        .load(Ordering::Relaxed),
                                });
                                Ok(path)
                            }
                        }
                    };
                    let _ = reply.send(result);
                }
                Command::Stop { reply } => {
                    let result = match active.take() {
                        None => Err(RecorderError::Failed("not recording".to_owned())),
                        Some(rec) => finish(rec, subscription, status),
                    };
                    let _ = reply.send(result);
                }
            }
        }
        let msg = subscription.recv_timeout(Duration::from_millis(20));
        if let Some(rec) = active.as_mut() {
            let mut ok = msg.is_none_or(|msg| {
                let written = rec.writer.write(&msg);
                rec.record_outcome(status, written)
            });
            while ok && let Ok(output) = outputs.try_recv() {
                let written = rec.writer.write_output(&output);
                ok = rec.record_outcome(status, written);
            }
            if !ok {
                active = None;
            }
        }
    }
    if let Some(rec) = active.take()
        && let Err(error) = finish(rec, subscription, status)
    {
        tracing::error!(%error, "recording not finished cleanly");
    }
}

/// A new recording at `path`, a regular file.
fn create(
    path: &std::path::Path,
    existing: Existing,
    meta: &RecordingMeta,
    options: &RecordingOptions,
) -> Result<RecordingWriter<BufWriter<File>>, String> {
    let file = super::safe_file::create_regular(path, existing).map_err(|e| e.to_string())?;
    RecordingWriter::with_options(BufWriter::with_capacity(1 << 20, file), meta, options)
        .map_err(|e| e.to_string())
}

fn finish(
    rec: Active,
    subscription: &Subscription<StreamMessage>,
    status: &RecorderStatus,
) -> Result<Value, RecorderError> {
    status.active.store(false, Ordering::Release);
    let messages = rec.writer.messages_written();
    let dropped = subscription.dropped() - rec.drops_at_start;
    let outputs_dropped =
        status.outputs_dropped.load(Ordering::Relaxed) - rec.output_drops_at_start;
    let summary = rec
        .writer
        .finish()
        .map_err(|e| RecorderError::Failed(format!("cannot finish {}: {e}", rec.path.display())))?;
    tracing::info!(path = %rec.path.display(), messages, dropped, "recording finished");
    let per_stream: serde_json::Map<String, Value> = summary
        .messages
        .iter()
        .map(|(kind, n)| (kind.name().to_owned(), Value::from(*n)))
        .collect();
    let duration_s = match (summary.start_ns, summary.end_ns) {
        (Some(start), Some(end)) => end.saturating_sub(start) as f64 * 1e-9,
        _ => 0.0,
    };
    Ok(json!({
        "path": rec.path,
        "messages": messages,
        "dropped": dropped,
        "outputs_dropped": outputs_dropped,
        "per_stream": per_stream,
        "duration_s": duration_s,
        "chunks": summary.chunks,
    }))
}
