//! The MCAP recorder: a thread with its own bus subscription (every message of every stream,
//! bounded queue, drop-oldest so a slow disk never stalls capture) that writes while recording.
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
use relight_core::recording::{RecordingMeta, RecordingWriter};
use serde_json::{Value, json};

use super::safe_file::Existing;

/// How long a request waits for the recorder thread's answer.
pub const ANSWER_TIMEOUT: Duration = Duration::from_secs(3);

enum Command {
    Start {
        path: PathBuf,
        existing: Existing,
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
    messages: AtomicU64,
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
        let status = Arc::new(RecorderStatus::default());
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let status = status.clone();
            let stop = stop.clone();
            std::thread::Builder::new()
                .name("recorder".into())
                .spawn(move || run(&subscription, &rx, &status, &stop, &meta))?
        };
        Ok(Self {
            commands,
            status,
            stop,
            thread: Some(thread),
        })
    }

    pub fn status(&self) -> &Arc<RecorderStatus> {
        &self.status
    }

    pub fn start(&self, path: PathBuf, existing: Existing) -> Result<PathBuf, RecorderError> {
        let (reply, answer) = bounded(1);
        self.send(
            Command::Start {
                path,
                existing,
                reply,
            },
            &answer,
        )
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
}

fn run(
    subscription: &Subscription<StreamMessage>,
    commands: &Receiver<Command>,
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
                    reply,
                } => {
                    let result = if active.is_some() {
                        Err(RecorderError::Busy(
                            "already recording; stop first".to_owned(),
                        ))
                    } else {
                        match create(&path, existing, meta) {
                            Err(message) => Err(RecorderError::File { path, message }),
                            Ok(writer) => {
                                // Discard what queued up before the start.
                                while subscription.try_recv().is_some() {}
                                *status.path.lock().unwrap_or_else(PoisonError::into_inner) =
                                    Some(path.clone());
                                status.messages.store(0, Ordering::Relaxed);
                                status.active.store(true, Ordering::Release);
                                tracing::info!(path = %path.display(), "recording started");
                                active = Some(Active {
                                    path: path.clone(),
                                    writer,
                                    drops_at_start: subscription.dropped(),
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
        let Some(msg) = subscription.recv_timeout(Duration::from_millis(20)) else {
            continue;
        };
        if let Some(rec) = active.as_mut() {
            match rec.writer.write(&msg) {
                Ok(()) => {
                    status.messages.fetch_add(1, Ordering::Relaxed);
                }
                Err(error) => {
                    tracing::error!(path = %rec.path.display(), %error, "recording stopped: write failed");
                    status.active.store(false, Ordering::Release);
                    active = None;
                }
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
) -> Result<RecordingWriter<BufWriter<File>>, String> {
    let file = super::safe_file::create_regular(path, existing).map_err(|e| e.to_string())?;
    RecordingWriter::new(BufWriter::with_capacity(1 << 20, file), meta).map_err(|e| e.to_string())
}

fn finish(
    rec: Active,
    subscription: &Subscription<StreamMessage>,
    status: &RecorderStatus,
) -> Result<Value, RecorderError> {
    status.active.store(false, Ordering::Release);
    let messages = rec.writer.messages_written();
    let dropped = subscription.dropped() - rec.drops_at_start;
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
        "per_stream": per_stream,
        "duration_s": duration_s,
        "chunks": summary.chunks,
    }))
}
