//! The roofline of `relightd bench --roofline`: what the adapter can do, and how close each pass
//! comes to it.
//!
//! Two micro-kernels (`shaders/roofline.wgsl`) measure the adapter's rates: `copy` its memory
//! bandwidth (bytes read plus bytes written per second) and `fma_rate` its arithmetic rate
//! (a fused multiply-add counts as two operations). Each engine states, per pass it ran in a
//! frame, the work that pass's algorithm must do ([`Work`], in [`RelitFrame::work`]): the bytes
//! it has to move at least once (every input read and every output written once, as with a
//! perfect cache) and the arithmetic it has to do. A pass's roofline time is that work at the
//! adapter's rates, the slower of the two; its *roofline fraction* is that time over the time
//! it took. 1 is the adapter's limit; a pass far below it is bound by something the model does
//! not count (latency, atomics, rasteriser setup, dispatch overhead).
//!
//! [`RelitFrame::work`]: crate::engine::RelitFrame::work

use std::time::Instant;

use bytemuck::{Pod, Zeroable};

use crate::gpu::{GpuContext, GpuError};
use crate::shaders;

/// What a pass's algorithm must do: bytes moved to or from memory and arithmetic operations.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Work {
    pub bytes: f64,
    pub ops: f64,
}

impl Work {
    pub fn new(bytes: f64, ops: f64) -> Self {
        Self { bytes, ops }
    }

    /// `count` repetitions of `self`.
    pub fn times(self, count: f64) -> Self {
        Self::new(self.bytes * count, self.ops * count)
    }
}

impl std::ops::Add for Work {
    type Output = Work;
    fn add(self, other: Work) -> Work {
        Work::new(self.bytes + other.bytes, self.ops + other.ops)
    }
}

/// Arithmetic per vertex of a raster pass: the position through a 4×4 matrix and the normal
/// through a 3×3 one, as multiply-adds.
const VERTEX_OPS: f64 = 2.0 * (16.0 + 9.0);
/// Bytes of a vertex the raster passes read (`GpuVertex`).
const VERTEX_BYTES: f64 = 32.0;

/// A raster pass: `vertices` read and transformed, `texels` of `texel_bytes` written once
/// (colour targets and depth). Rasterisation and depth testing are not counted: they are
/// fixed-function on a GPU and have no algorithmic minimum to compare against.
pub fn raster(vertices: u32, texels: u64, texel_bytes: u64) -> Work {
    Work::new(
        f64::from(vertices) * VERTEX_BYTES + (texels * texel_bytes) as f64,
        f64::from(vertices) * VERTEX_OPS,
    )
}

/// A copy of `bytes`: read once, written once.
pub fn copy(bytes: u64) -> Work {
    Work::new(2.0 * bytes as f64, 0.0)
}

/// A pass's work in one frame, under the label its GPU timing carries (`gpu.<pass>`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassWork {
    pub pass: &'static str,
    pub work: Work,
}

/// The adapter's measured rates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rates {
    /// Bytes read plus bytes written per second by a streaming copy.
    pub bytes_per_s: f64,
    /// Arithmetic operations per second (a fused multiply-add is two).
    pub ops_per_s: f64,
}

/// Which of the two rates bounds a pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bound {
    Memory,
    Arithmetic,
}

impl Bound {
    pub fn name(self) -> &'static str {
        match self {
            Bound::Memory => "memory",
            Bound::Arithmetic => "alu",
        }
    }
}

impl Rates {
    /// The time `work` takes at these rates, in ms, and which rate bounds it.
    pub fn roofline_ms(&self, work: Work) -> (f64, Bound) {
        let memory = work.bytes / self.bytes_per_s;
        let arithmetic = work.ops / self.ops_per_s;
        if memory >= arithmetic {
            (memory * 1e3, Bound::Memory)
        } else {
            (arithmetic * 1e3, Bound::Arithmetic)
        }
    }

    /// The roofline time of `work` over `ms`, the time it took (`NaN` for a time of zero).
    pub fn fraction(&self, work: Work, ms: f64) -> f64 {
        if ms > 0.0 {
            self.roofline_ms(work).0 / ms
        } else {
            f64::NAN
        }
    }
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Uniform {
    size: [u32; 4],
}

/// Elements (vec4) the copy kernel streams: 16 MiB each way, past any cache.
const COPY_ELEMENTS: u32 = 1 << 20;
/// Invocations and iterations of the FMA kernel: 8 vec4 chains each, 2 ops per lane.
const FMA_INVOCATIONS: u32 = 1 << 16;
const FMA_ITERATIONS: u32 = 256;
/// Each kernel repeats until one measurement lasts at least this long.
const MIN_MEASURE_S: f64 = 0.05;

/// Measure the adapter's bandwidth and arithmetic rate: each kernel warms up once, then runs
/// in batches doubled until a batch lasts `MIN_MEASURE_S`; the best of three such batches
/// counts (the others were disturbed by something else).
pub fn measure(ctx: &GpuContext) -> Result<Rates, GpuError> {
    let device = &ctx.device;
    let buffer = |label, usage| {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: u64::from(COPY_ELEMENTS) * 16,
            usage,
            mapped_at_creation: false,
        })
    };
    use wgpu::BufferUsages as U;
    let source = buffer("roofline source", U::STORAGE | U::COPY_DST);
    let output = buffer("roofline output", U::STORAGE);
    ctx.queue.write_buffer(
        &source,
        0,
        bytemuck::cast_slice(&vec![0.5f32; COPY_ELEMENTS as usize * 4]),
    );
    let uniform = |size: [u32; 4]| {
        let buffer = shaders::params_buffer(device, "roofline", size_of::<Uniform>());
        ctx.queue
            .write_buffer(&buffer, 0, bytemuck::bytes_of(&Uniform { size }));
        buffer
    };
    let copy_uniform = uniform([COPY_ELEMENTS, 0, 0, 0]);
    let fma_uniform = uniform([FMA_INVOCATIONS, FMA_ITERATIONS, 0, 0]);
    let kernel = |entry: &str, uniform: &wgpu::Buffer, invocations: u32| {
        let pipeline = shaders::compute_pipeline_at(device, "roofline", shaders::ROOFLINE, entry);
        let group = shaders::pipeline_bind_group(
            device,
            &pipeline,
            "roofline",
            &[
                uniform.as_entire_binding(),
                source.as_entire_binding(),
                output.as_entire_binding(),
            ],
        );
        best_seconds(ctx, &pipeline, &group, invocations.div_ceil(64))
    };
    let copy_s = kernel("copy", &copy_uniform, COPY_ELEMENTS)?;
    let fma_s = kernel("fma_rate", &fma_uniform, FMA_INVOCATIONS)?;
    Ok(Rates {
        bytes_per_s: f64::from(COPY_ELEMENTS) * 32.0 / copy_s,
        ops_per_s: f64::from(FMA_INVOCATIONS) * f64::from(FMA_ITERATIONS) * 8.0 * 4.0 * 2.0 / fma_s,
    })
}

/// Seconds one dispatch of `groups` workgroups (split into rows of at most 32 768) takes.
fn best_seconds(
    ctx: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    group: &wgpu::BindGroup,
    groups: u32,
) -> Result<f64, GpuError> {
    let run = |count: u32| -> Result<f64, GpuError> {
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("roofline"),
            });
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, group, &[]);
            let x = groups.min(32_768);
            for _ in 0..count {
                pass.dispatch_workgroups(x, groups.div_ceil(x), 1);
            }
        }
        let started = Instant::now();
        ctx.queue.submit([encoder.finish()]);
        ctx.wait()?;
        Ok(started.elapsed().as_secs_f64())
    };
    run(1)?;
    let mut count = 1;
    while run(count)? < MIN_MEASURE_S && count < 1 << 16 {
        count *= 2;
    }
    let mut best = f64::INFINITY;
    for _ in 0..3 {
        best = best.min(run(count)? / f64::from(count));
    }
    Ok(best)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_slower_rate_bounds_and_the_fraction_is_roofline_over_measured() {
        let rates = Rates {
            bytes_per_s: 1e9,
            ops_per_s: 1e10,
        };
        // 1 MB at 1 GB/s: 1 ms; 1 Mop at 10 Gop/s: 0.1 ms.
        let work = Work::new(1e6, 1e6);
        assert_eq!(rates.roofline_ms(work), (1.0, Bound::Memory));
        assert!((rates.fraction(work, 4.0) - 0.25).abs() < 1e-12);
        let (ms, bound) = rates.roofline_ms(Work::new(0.0, 1e8));
        assert!((ms - 10.0).abs() < 1e-9);
        assert_eq!(bound, Bound::Arithmetic);
        assert!(rates.fraction(work, 0.0).is_nan());
        assert_eq!(
            Work::new(1.0, 2.0).times(3.0) + Work::new(1.0, 1.0),
            Work::new(4.0, 7.0)
        );
    }
}
