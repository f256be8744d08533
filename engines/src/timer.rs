//! GPU pass timing with timestamp queries, where the adapter supports them (lavapipe does):
//! each timed pass writes a timestamp at its start and end; after the frame's last submission
//! the pairs are resolved, read back and summed per label into `gpu.<label>` pass timings.
//! Adapters without timestamp queries get no `gpu.*` entries; the wall-clock timings remain.
//!
//! With [`GpuContext::set_wait_per_pass`] the same labels are timed by waiting instead: each
//! timed pass first submits what its encoder holds and waits for the queue, so a pass's time
//! runs from its start until the next timed pass starts (the last one's until the frame's
//! read-back has arrived), whatever else the queue did in between included.

use std::sync::Arc;
use std::time::Instant;

use crate::engine::PassTiming;
use crate::gpu::{GpuContext, GpuError};

/// Timestamp pairs one frame can hold (a pass per shadow-map face adds one).
const MAX_PASSES: u32 = 512;

#[derive(Debug)]
pub struct GpuTimer {
    ctx: Arc<GpuContext>,
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    staging: wgpu::Buffer,
    labels: Vec<&'static str>,
    period_ns: f64,
    /// This frame times passes by waiting ([`GpuContext::waits_per_pass`] when it started).
    waiting: bool,
    /// While waiting: the pass running since its boundary, and the passes finished.
    running: Option<(&'static str, Instant)>,
    waited: Vec<(&'static str, f64)>,
    /// A wait that failed (a lost device), for [`read`](Self::read) to return.
    failed: Option<GpuError>,
}

impl GpuTimer {
    /// `None` when the adapter has no timestamp queries.
    pub fn new(ctx: &Arc<GpuContext>) -> Option<Self> {
        if !ctx.timestamps {
            return None;
        }
        let size = u64::from(2 * MAX_PASSES) * 8;
        let buffer = |label, usage| {
            ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        Some(Self {
            ctx: ctx.clone(),
            set: ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("pass timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: 2 * MAX_PASSES,
            }),
            resolve: buffer(
                "timestamps resolve",
                wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            ),
            staging: buffer(
                "timestamps staging",
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            ),
            labels: Vec::new(),
            period_ns: f64::from(ctx.queue.get_timestamp_period()),
            waiting: false,
            running: None,
            waited: Vec::new(),
            failed: None,
        })
    }

    /// Start a frame.
    pub fn reset(&mut self) {
        self.labels.clear();
        self.waiting = self.ctx.waits_per_pass();
        self.running = None;
        self.waited.clear();
        self.failed = None;
    }

    /// While waiting: submit what `encoder` holds, wait for the queue, end the running pass and
    /// start `label`'s. False when this frame uses timestamps.
    fn boundary(&mut self, encoder: &mut wgpu::CommandEncoder, label: &'static str) -> bool {
        if !self.waiting {
            return false;
        }
        let before = std::mem::replace(
            encoder,
            self.ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor::default()),
        );
        self.ctx.queue.submit([before.finish()]);
        if let Err(error) = self.ctx.wait() {
            self.failed.get_or_insert(error);
        }
        self.end_running();
        self.running = Some((label, Instant::now()));
        true
    }

    fn end_running(&mut self) {
        if let Some((label, since)) = self.running.take() {
            self.waited
                .push((label, since.elapsed().as_secs_f64() * 1e3));
        }
    }

    /// Query indices (start, end) for a pass labelled `label`, or `None` when full.
    fn slot(&mut self, label: &'static str) -> Option<(u32, u32)> {
        let n = self.labels.len() as u32;
        (n < MAX_PASSES).then(|| {
            self.labels.push(label);
            (2 * n, 2 * n + 1)
        })
    }

    /// Time the compute pass about to begin on `encoder` (see the module docs).
    pub fn compute(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        label: &'static str,
    ) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        if self.boundary(encoder, label) {
            return None;
        }
        let (start, end) = self.slot(label)?;
        Some(wgpu::ComputePassTimestampWrites {
            query_set: &self.set,
            beginning_of_pass_write_index: Some(start),
            end_of_pass_write_index: Some(end),
        })
    }

    /// Time the render pass about to begin on `encoder` (see the module docs).
    pub fn render(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        label: &'static str,
    ) -> Option<wgpu::RenderPassTimestampWrites<'_>> {
        if self.boundary(encoder, label) {
            return None;
        }
        let (start, end) = self.slot(label)?;
        Some(wgpu::RenderPassTimestampWrites {
            query_set: &self.set,
            beginning_of_pass_write_index: Some(start),
            end_of_pass_write_index: Some(end),
        })
    }

    /// Resolve this frame's queries (encode after the last timed pass).
    pub fn resolve(&self, encoder: &mut wgpu::CommandEncoder) {
        if self.waiting {
            return;
        }
        let n = 2 * self.labels.len() as u32;
        if n > 0 {
            encoder.resolve_query_set(&self.set, 0..n, &self.resolve, 0);
        }
    }

    /// Read the resolved times (after the submission holding [`resolve`](Self::resolve)) and
    /// append `gpu.<label>` timings, summed per label, in first-use order. While waiting, call
    /// it once the frame's read-back has arrived: that ends the last pass; a wait that failed
    /// is returned here.
    pub fn read(&mut self, timings: &mut Vec<PassTiming>) -> Result<(), GpuError> {
        if let Some(error) = self.failed.take() {
            return Err(error);
        }
        let times: Vec<(&'static str, f64)> = if self.waiting {
            self.end_running();
            std::mem::take(&mut self.waited)
        } else {
            let n = self.labels.len();
            if n == 0 {
                return Ok(());
            }
            let ticks: Vec<u64> =
                self.ctx
                    .read_back(&self.resolve, &self.staging, 16 * n as u64, |bytes| {
                        bytes
                            .chunks_exact(8)
                            .map(|b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
                            .collect()
                    })?;
            self.labels
                .iter()
                .zip(ticks.chunks_exact(2))
                .map(|(label, pair)| {
                    let ms = pair[1].saturating_sub(pair[0]) as f64 * self.period_ns / 1e6;
                    (*label, ms)
                })
                .collect()
        };
        let mut sums: Vec<(&'static str, f64)> = Vec::new();
        for (label, ms) in times {
            match sums.iter_mut().find(|(l, _)| *l == label) {
                Some((_, total)) => *total += ms,
                None => sums.push((label, ms)),
            }
        }
        timings.extend(sums.into_iter().map(|(pass, ms)| PassTiming { pass, ms }));
        Ok(())
    }
}

/// A compute pass labelled `label`, timed under it when there is a timer (see the module docs).
pub(crate) fn timed_pass<'e>(
    encoder: &'e mut wgpu::CommandEncoder,
    timer: &mut Option<GpuTimer>,
    label: &'static str,
) -> wgpu::ComputePass<'e> {
    let timestamp_writes = timer.as_mut().and_then(|t| t.compute(encoder, label));
    encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
        label: Some(label),
        timestamp_writes,
    })
}
