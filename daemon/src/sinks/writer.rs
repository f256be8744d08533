//! The output writer: a thread that encodes and writes composite PNGs and snapshots, so the
//! render thread never waits on a disk, a full file system or a path that blocks. Its queue is
//! bounded; a frame offered while it is full is dropped and counted, never waited for.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use crossbeam_channel::Sender;
use relight_core::Image;

use super::png_out::write_png_as;
use super::safe_file::Existing;
use crate::worker::Worker;

/// Writes queued before new ones are dropped.
pub const QUEUE_WRITES: usize = 4;

/// One image to write under `dir` as `file_name`; `reply`, when given, hears where it went.
#[derive(Debug)]
pub struct Write {
    pub dir: PathBuf,
    pub file_name: String,
    pub image: Image,
    /// Whether an existing file of that name is replaced.
    pub existing: Existing,
    pub reply: Option<Sender<Result<Vec<PathBuf>, WriteFailure>>>,
}

/// Why an image was not written.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WriteFailure {
    /// The queue was full: try again.
    #[error("the image writer is behind ({QUEUE_WRITES} writes queued); not written")]
    Behind,
    /// Creating the directory or the file, or writing it, failed; the message names the path
    /// and the reason.
    #[error("{0}")]
    Io(String),
}

/// Handle to the writer thread; dropping it writes what is queued and joins.
#[derive(Debug)]
pub struct ImageWriter {
    worker: Worker<Write>,
    dropped: AtomicU64,
    failed: Arc<AtomicU64>,
}

impl ImageWriter {
    pub fn spawn() -> std::io::Result<Self> {
        let failed = Arc::new(AtomicU64::new(0));
        let worker = {
            let failed = failed.clone();
            Worker::spawn("image-writer", QUEUE_WRITES, move |job: Write| {
                let result = write(&job);
                if let Err(error) = &result {
                    let n = failed.fetch_add(1, Ordering::Relaxed);
                    if n.is_power_of_two() || n == 0 {
                        tracing::warn!(%error, failed = n + 1, "image not written");
                    }
                }
                if let Some(reply) = job.reply {
                    let _ = reply.send(result);
                }
            })?
        };
        Ok(Self {
            worker,
            dropped: AtomicU64::new(0),
            failed,
        })
    }

    /// Queue `job` without waiting. A full queue drops it (counted) and answers its reply with
    /// an error saying so.
    pub fn offer(&self, job: Write) {
        if let Err(job) = self.worker.offer(job) {
            self.dropped.fetch_add(1, Ordering::Relaxed);
            if let Some(reply) = job.reply {
                let _ = reply.send(Err(WriteFailure::Behind));
            }
        }
    }

    /// Images dropped because the queue was full.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Images whose write failed.
    pub fn failed(&self) -> u64 {
        self.failed.load(Ordering::Relaxed)
    }
}

fn write(job: &Write) -> Result<Vec<PathBuf>, WriteFailure> {
    std::fs::create_dir_all(&job.dir)
        .map_err(|e| WriteFailure::Io(format!("cannot create {}: {e}", job.dir.display())))?;
    let path = job.dir.join(&job.file_name);
    write_png_as(&path, &job.image, job.existing).map_err(|e| WriteFailure::Io(e.to_string()))?;
    Ok(vec![path])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossbeam_channel::bounded;
    use relight_core::PixelFormat;

    #[test]
    fn writes_in_order_and_reports_a_refused_path() {
        let dir = tempfile::tempdir().unwrap();
        let writer = ImageWriter::spawn().unwrap();
        let fifo = dir.path().join("f.png");
        rustix::fs::mknodat(
            rustix::fs::CWD,
            &fifo,
            rustix::fs::FileType::Fifo,
            rustix::fs::Mode::from_raw_mode(0o644),
            0,
        )
        .unwrap();
        let (reply, answers) = bounded(2);
        for name in ["f.png", "ok.png"] {
            writer.offer(Write {
                dir: dir.path().to_path_buf(),
                file_name: name.into(),
                image: Image::new(2, 2, PixelFormat::Rgb8),
                existing: Existing::Replace,
                reply: Some(reply.clone()),
            });
        }
        let fifo_answer = answers.recv().unwrap();
        assert!(fifo_answer.unwrap_err().to_string().contains("FIFO"));
        assert_eq!(
            answers.recv().unwrap().unwrap(),
            vec![dir.path().join("ok.png")]
        );
        assert_eq!((writer.failed(), writer.dropped()), (1, 0));

        // A snapshot without `overwrite` does not replace a file of the same name.
        writer.offer(Write {
            dir: dir.path().to_path_buf(),
            file_name: "ok.png".into(),
            image: Image::new(2, 2, PixelFormat::Rgb8),
            existing: Existing::Refuse,
            reply: Some(reply),
        });
        let refused = answers.recv().unwrap().unwrap_err();
        assert!(
            matches!(&refused, WriteFailure::Io(m) if m.contains("it exists")),
            "{refused}"
        );
    }
}
