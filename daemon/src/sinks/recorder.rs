//! The MCAP recorder: a thread with its own bus subscription (every message of every stream,
//! bounded queue, drop-oldest so a slow disk never stalls capture) that writes while recording.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender, bounded};
use relight_core::StreamMessage;
use relight_core::bus::{Bus, Subscription};
use relight_core::recording::{RecordingMeta, RecordingWriter};
use serde_json::{Value, json};

enum Command {
    Start {
        path: PathBuf,
        reply: Sender<Result<PathBuf, String>>,
    },
    Stop {
        reply: Sender<Result<Value, String>>,
    },
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

    pub fn start(&self, path: PathBuf) -> Result<PathBuf, String> {
        let (reply, answer) = bounded(1);
        self.send(Command::Start { path, reply }, &answer)
    }

    pub fn stop_recording(&self) -> Result<Value, String> {
        let (reply, answer) = bounded(1);
        self.send(Command::Stop { reply }, &answer)
    }

    fn send<T>(&self, command: Command, answer: &Receiver<Result<T, String>>) -> Result<T, String> {
        self.commands
            .send(command)
            .map_err(|_| "the recorder thread has ended".to_owned())?;
        answer
            .recv_timeout(Duration::from_secs(10))
            .map_err(|_| "the recorder did not answer within 10 s".to_owned())?
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
    writer: RecordingWriter<std::io::BufWriter<std::fs::File>>,
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
                Command::Start { path, reply } => {
                    let result = if active.is_some() {
                        Err("already recording; stop first".to_owned())
                    } else {
                        RecordingWriter::create(&path, meta)
                            .map(|writer| {
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
                                path
                            })
                            .map_err(|e| format!("cannot start recording: {e}"))
                    };
                    let _ = reply.send(result);
                }
                Command::Stop { reply } => {
                    let result = match active.take() {
                        None => Err("not recording".to_owned()),
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

fn finish(
    rec: Active,
    subscription: &Subscription<StreamMessage>,
    status: &RecorderStatus,
) -> Result<Value, String> {
    status.active.store(false, Ordering::Release);
    let messages = rec.writer.messages_written();
    let dropped = subscription.dropped() - rec.drops_at_start;
    let summary = rec
        .writer
        .finish()
        .map_err(|e| format!("cannot finish {}: {e}", rec.path.display()))?;
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
