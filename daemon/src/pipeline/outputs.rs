//! The sinks stage: the composite to the configured output directory every `every_n` frames,
//! and to whoever asked for a snapshot. Both are handed to the image writer's thread
//! ([`ImageWriter`]); the render thread never touches a file.

use std::path::PathBuf;
use std::sync::Mutex;
use std::time::Instant;

use crossbeam_channel::{Receiver, Sender};
use relight_engines::RelitFrame;

use crate::config::{Config, OutputConfig};
use crate::lock;
use crate::sinks::safe_file::Existing;
use crate::sinks::writer::{ImageWriter, Write, WriteFailure};
use crate::timing::StageTimer;

/// A `snapshot` request from the control socket, answered with the files written.
#[derive(Debug)]
pub struct SnapshotRequest {
    pub dir: PathBuf,
    pub existing: Existing,
    pub reply: Sender<Result<Vec<PathBuf>, WriteFailure>>,
}

#[derive(Debug)]
pub struct Outputs {
    snapshots: Receiver<SnapshotRequest>,
    timer: StageTimer,
}

impl Outputs {
    pub fn new(snapshots: Receiver<SnapshotRequest>, timer: StageTimer) -> Self {
        Self { snapshots, timer }
    }

    /// Frame `seq`'s composite: to the output directory when it is one of every `every_n`,
    /// and to the snapshots asked for.
    pub fn composite(
        &self,
        config: &Mutex<Config>,
        writer: &ImageWriter,
        seq: u64,
        relit: &RelitFrame,
    ) {
        let start = Instant::now();
        let OutputConfig { dir, every_n } = lock(config).output.clone();
        if let Some(dir) = dir
            && seq.is_multiple_of(u64::from(every_n.max(1)))
        {
            writer.offer(Write {
                dir,
                file_name: format!("composite_{seq:06}.png"),
                image: relit.composite.clone(),
                existing: Existing::Replace,
                reply: None,
            });
        }
        self.serve_snapshots(writer, relit, true);
        self.timer.record(start.elapsed().as_secs_f64() * 1e3);
    }

    /// Hand snapshot requests the last rendered frame, for the writer to write. Called after
    /// each frame, and on every idle turn of the loop (`fresh = false`, once a frame exists), so
    /// a paused or finished replay can still be snapshotted.
    pub fn serve_snapshots(&self, writer: &ImageWriter, relit: &RelitFrame, fresh: bool) {
        if !fresh && relit.composite.pixel_count() == 0 {
            return;
        }
        while let Ok(request) = self.snapshots.try_recv() {
            writer.offer(Write {
                dir: request.dir,
                file_name: format!("snapshot_{:06}_composite.png", relit.seq),
                image: relit.composite.clone(),
                existing: request.existing,
                reply: Some(request.reply),
            });
        }
    }
}
