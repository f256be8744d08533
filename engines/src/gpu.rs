//! The GPU context every engine shares: adapter choice, device creation, limit checks with
//! errors that name the setting to lower, device-loss detection, and buffer readback.
//!
//! Adapter choice: `RELIGHT_ADAPTER` (a case-insensitive substring of the adapter's name, or
//! `#N` for the N-th adapter as listed in the error message) forces one; otherwise a discrete GPU
//! is preferred, then an integrated one, then a virtual one, then a CPU implementation
//! (lavapipe, llvmpipe). OpenGL adapters are only considered when no Vulkan driver is installed. Machines without a GPU run on
//! lavapipe (Debian `mesa-vulkan-drivers`), which is real Vulkan on the CPU.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// Environment variable that forces an adapter.
pub const ADAPTER_ENV: &str = "RELIGHT_ADAPTER";

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no GPU adapter found (neither Vulkan nor OpenGL): install your GPU's driver, or the \
         Debian package `mesa-vulkan-drivers` for lavapipe, a Vulkan driver that runs on the CPU"
    )]
    NoAdapter,
    #[error("{ADAPTER_ENV}=`{wanted}` matches none of the adapters: {available}")]
    AdapterNotFound { wanted: String, available: String },
    #[error(
        "adapter `{adapter}` allows {limit} = {allowed}, this setting needs {needed}: lower {setting}"
    )]
    Limit {
        adapter: String,
        limit: &'static str,
        needed: u64,
        allowed: u64,
        setting: String,
    },
    #[error("adapter `{adapter}` lacks {feature}, which {needed_by} needs")]
    Feature {
        adapter: String,
        feature: String,
        needed_by: String,
    },
    #[error("requesting a device from `{adapter}`: {reason}")]
    Device { adapter: String, reason: String },
    #[error("GPU device lost ({reason}); rebuild the engine to recover")]
    Lost { reason: String },
    #[error("GPU error: {0}")]
    Validation(String),
    #[error("reading back from the GPU: {0}")]
    Readback(String),
}

/// An adapter as listed for the user.
#[derive(Debug, Clone)]
pub struct AdapterSummary {
    pub index: usize,
    pub name: String,
    pub backend: wgpu::Backend,
    pub device_type: wgpu::DeviceType,
}

impl std::fmt::Display for AdapterSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "#{} {} ({:?}, {:?})",
            self.index, self.name, self.backend, self.device_type
        )
    }
}

/// The device, its queue and what is known about them.
#[derive(Debug)]
pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
    /// Whether passes can be timed with timestamp queries.
    pub timestamps: bool,
    /// Whether pass timers time each pass by waiting for it instead ([`Self::set_wait_per_pass`]).
    wait_per_pass: AtomicBool,
    lost: Arc<Mutex<Option<String>>>,
    errored: Arc<Mutex<Option<String>>>,
}

/// Features a device is given when its adapter has them: timestamps for the pass timer; f32
/// filtering and zero borders for `dvct`'s filtered voxel mips ([`GpuContext::require_features`]).
/// Vulkan drivers, lavapipe included, have all three.
const OPTIONAL_FEATURES: wgpu::Features = wgpu::Features::TIMESTAMP_QUERY
    .union(wgpu::Features::FLOAT32_FILTERABLE)
    .union(wgpu::Features::ADDRESS_MODE_CLAMP_TO_BORDER);

/// Vulkan adapters, or OpenGL ones when there is no Vulkan driver (probing GL needs a display
/// or EGL device and complains loudly on headless machines, so it is only tried as a fallback).
fn enumerate() -> Vec<wgpu::Adapter> {
    for backends in [wgpu::Backends::VULKAN, wgpu::Backends::GL] {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends,
            ..wgpu::InstanceDescriptor::new_without_display_handle_from_env()
        });
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        if !adapters.is_empty() {
            return adapters;
        }
    }
    Vec::new()
}

/// Every adapter this machine offers, numbered as `RELIGHT_ADAPTER=#N` takes them
/// (`relightd gpu`), and the index of the one chosen without `RELIGHT_ADAPTER`.
pub fn adapters() -> (Vec<AdapterSummary>, Option<usize>) {
    let adapters = enumerate();
    let preferred = (0..adapters.len()).min_by_key(|&i| rank(&adapters[i].get_info()));
    (summarize(&adapters), preferred)
}

/// GPU device nodes present in `/dev` (DRM render nodes, NVIDIA's per-GPU nodes): when the
/// chosen adapter is a CPU although these exist, the GPU's Vulkan driver is missing or the
/// service's device policy hides them.
pub fn gpu_device_nodes() -> Vec<std::path::PathBuf> {
    let mut nodes = Vec::new();
    for (dir, prefix) in [("/dev/dri", "renderD"), ("/dev", "nvidia")] {
        let Ok(entries) = std::fs::read_dir(dir) else {
            continue;
        };
        for entry in entries.flatten() {
            let name = entry.file_name();
            let name = name.to_string_lossy();
            let is_node = name
                .strip_prefix(prefix)
                .is_some_and(|rest| !rest.is_empty() && rest.bytes().all(|b| b.is_ascii_digit()));
            if is_node {
                nodes.push(entry.path());
            }
        }
    }
    nodes.sort();
    nodes
}

fn is_gpu(device_type: wgpu::DeviceType) -> bool {
    matches!(
        device_type,
        wgpu::DeviceType::DiscreteGpu
            | wgpu::DeviceType::IntegratedGpu
            | wgpu::DeviceType::VirtualGpu
    )
}

/// The adapters as listed to the user (and numbered for `RELIGHT_ADAPTER=#N`).
fn summarize(adapters: &[wgpu::Adapter]) -> Vec<AdapterSummary> {
    adapters
        .iter()
        .enumerate()
        .map(|(index, a)| {
            let info = a.get_info();
            AdapterSummary {
                index,
                name: info.name,
                backend: info.backend,
                device_type: info.device_type,
            }
        })
        .collect()
}

fn rank(info: &wgpu::AdapterInfo) -> (u8, u8) {
    let kind = match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    };
    let backend = match info.backend {
        wgpu::Backend::Vulkan => 0,
        _ => 1,
    };
    (kind, backend)
}

impl GpuContext {
    /// Choose an adapter (see the module docs) and open a device with the adapter's own limits,
    /// so that engines can check what they need against them and say which setting to lower.
    pub fn new() -> Result<Self, GpuError> {
        let wanted = std::env::var(ADAPTER_ENV)
            .ok()
            .filter(|s| !s.trim().is_empty());
        Self::with_adapter(wanted.as_deref())
    }

    pub fn with_adapter(wanted: Option<&str>) -> Result<Self, GpuError> {
        let adapters = enumerate();
        if adapters.is_empty() {
            return Err(GpuError::NoAdapter);
        }
        let summaries = summarize(&adapters);
        let chosen = match wanted {
            Some(wanted) => {
                let by_index = wanted
                    .strip_prefix('#')
                    .and_then(|n| n.parse::<usize>().ok());
                let needle = wanted.to_lowercase();
                summaries
                    .iter()
                    .position(|s| {
                        by_index.map_or_else(
                            || s.name.to_lowercase().contains(&needle),
                            |i| s.index == i,
                        )
                    })
                    .ok_or_else(|| GpuError::AdapterNotFound {
                        wanted: wanted.to_owned(),
                        available: summaries
                            .iter()
                            .map(ToString::to_string)
                            .collect::<Vec<_>>()
                            .join(", "),
                    })?
            }
            None => (0..adapters.len())
                .min_by_key(|&i| rank(&adapters[i].get_info()))
                .unwrap_or(0),
        };
        let adapter = &adapters[chosen];
        let info = adapter.get_info();
        let limits = adapter.limits();
        let required_features = adapter.features() & OPTIONAL_FEATURES;
        let timestamps = required_features.contains(wgpu::Features::TIMESTAMP_QUERY);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("relight"),
            required_features,
            required_limits: limits.clone(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| GpuError::Device {
            adapter: info.name.clone(),
            reason: e.to_string(),
        })?;
        let lost = Arc::new(Mutex::new(None));
        let lost_flag = lost.clone();
        device.set_device_lost_callback(move |reason, message| {
            tracing::error!(?reason, %message, "GPU device lost");
            if let Ok(mut lost) = lost_flag.lock() {
                *lost = Some(format!("{reason:?}: {message}"));
            }
        });
        let errored = Arc::new(Mutex::new(None));
        let error_slot = errored.clone();
        device.on_uncaptured_error(Arc::new(move |error: wgpu::Error| {
            tracing::error!(%error, "GPU error");
            if let Ok(mut slot) = error_slot.lock() {
                slot.get_or_insert_with(|| error.to_string());
            }
        }));
        tracing::info!(
            adapter = %info.name,
            backend = ?info.backend,
            device_type = ?info.device_type,
            timestamps,
            "GPU context ready"
        );
        if info.device_type == wgpu::DeviceType::Cpu {
            let gpus: Vec<String> = summaries
                .iter()
                .filter(|s| is_gpu(s.device_type))
                .map(ToString::to_string)
                .collect();
            if !gpus.is_empty() {
                tracing::warn!(
                    adapter = %info.name,
                    "rendering on a CPU adapter although GPU adapters exist ({}); choose one with {ADAPTER_ENV}=#N (`relightd gpu` lists them)",
                    gpus.join(", ")
                );
            } else if let nodes @ [_, ..] = gpu_device_nodes().as_slice() {
                tracing::warn!(
                    adapter = %info.name,
                    "rendering on a CPU adapter although GPU device nodes exist ({}): no Vulkan driver takes them; install the GPU's Vulkan driver (or, under systemd, check DeviceAllow)",
                    nodes.iter().map(|n| n.display().to_string()).collect::<Vec<_>>().join(", ")
                );
            }
        }
        Ok(Self {
            device,
            queue,
            info,
            limits,
            timestamps,
            wait_per_pass: AtomicBool::new(false),
            lost,
            errored,
        })
    }

    /// Time every pass by submitting what comes before it and waiting for the queue, instead of
    /// by timestamp queries (`relightd bench --pass-times wait`). A frame then overlaps nothing,
    /// so its total is slower, but each pass's time is its own: lavapipe writes a compute pass's
    /// timestamps before its shader threads have finished, so on it the later passes of a
    /// submission read almost nothing and the earlier ones their time. Read by each
    /// [`GpuTimer`](crate::timer::GpuTimer) when its frame starts.
    pub fn set_wait_per_pass(&self, wait: bool) {
        self.wait_per_pass.store(wait, Ordering::Relaxed);
    }

    /// See [`Self::set_wait_per_pass`].
    pub fn waits_per_pass(&self) -> bool {
        self.wait_per_pass.load(Ordering::Relaxed)
    }

    /// Whether the adapter is a software rasteriser (lavapipe, llvmpipe): its "GPU" passes run
    /// on the CPU's own cores.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// An error naming what `needed_by` needs unless the device has every one of `features`.
    pub fn require_features(
        &self,
        features: wgpu::Features,
        needed_by: &str,
    ) -> Result<(), GpuError> {
        let missing = features - self.device.features();
        if missing.is_empty() {
            Ok(())
        } else {
            Err(GpuError::Feature {
                adapter: self.info.name.clone(),
                feature: format!("{missing:?}"),
                needed_by: needed_by.to_owned(),
            })
        }
    }

    /// Check that `needed` fits the adapter's `limit` (one of the names below); the error
    /// names `setting` as the thing to lower.
    pub fn require(&self, limit: &'static str, needed: u64, setting: &str) -> Result<(), GpuError> {
        let l = &self.limits;
        let allowed = match limit {
            "max_texture_dimension_2d" => u64::from(l.max_texture_dimension_2d),
            "max_texture_dimension_3d" => u64::from(l.max_texture_dimension_3d),
            "max_texture_array_layers" => u64::from(l.max_texture_array_layers),
            "max_storage_buffer_binding_size" => l.max_storage_buffer_binding_size,
            "max_buffer_size" => l.max_buffer_size,
            "max_compute_workgroups_per_dimension" => {
                u64::from(l.max_compute_workgroups_per_dimension)
            }
            "max_color_attachment_bytes_per_sample" => {
                u64::from(l.max_color_attachment_bytes_per_sample)
            }
            _ => u64::MAX,
        };
        if needed <= allowed {
            Ok(())
        } else {
            Err(GpuError::Limit {
                adapter: self.info.name.clone(),
                limit,
                needed,
                allowed,
                setting: setting.to_owned(),
            })
        }
    }

    /// `Err` once the device is lost or an uncaptured error happened; engines call this after
    /// submitting, so the pipeline can rebuild them.
    pub fn check(&self) -> Result<(), GpuError> {
        if let Some(reason) = self.lost.lock().ok().and_then(|l| l.clone()) {
            return Err(GpuError::Lost { reason });
        }
        if let Some(error) = self.errored.lock().ok().and_then(|mut e| e.take()) {
            return Err(GpuError::Validation(error));
        }
        Ok(())
    }

    /// Whether the device is gone for good (a validation error is not).
    pub fn is_lost(&self) -> bool {
        self.lost.lock().map(|l| l.is_some()).unwrap_or(true)
    }

    /// Block until every submitted command has finished (for timing whole passes).
    pub fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        self.check()
    }

    /// An uninitialised buffer of `size` bytes.
    pub fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        })
    }

    /// A buffer holding `contents`.
    pub fn buffer_with(
        &self,
        label: &str,
        contents: &[u8],
        usage: wgpu::BufferUsages,
    ) -> wgpu::Buffer {
        wgpu::util::DeviceExt::create_buffer_init(
            &self.device,
            &wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            },
        )
    }

    /// Copy `size` bytes of `source` into `staging` (MAP_READ | COPY_DST, at least `size`),
    /// wait, and hand the bytes to `read`.
    pub fn read_back<T>(
        &self,
        source: &wgpu::Buffer,
        staging: &wgpu::Buffer,
        size: u64,
        read: impl FnOnce(&[u8]) -> T,
    ) -> Result<T, GpuError> {
        self.read_back_all(&[(source, 0..size)], staging, read)
    }

    /// [`read_back`](Self::read_back) of byte ranges of several buffers (each bound a multiple
    /// of 4), laid end to end in `staging` in one copy and one wait: `read` gets them in order.
    pub fn read_back_all<T>(
        &self,
        sources: &[(&wgpu::Buffer, std::ops::Range<u64>)],
        staging: &wgpu::Buffer,
        read: impl FnOnce(&[u8]) -> T,
    ) -> Result<T, GpuError> {
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("readback"),
            });
        let mut size = 0;
        for (source, bytes) in sources {
            let length = bytes.end - bytes.start;
            encoder.copy_buffer_to_buffer(source, bytes.start, staging, size, length);
            size += length;
        }
        self.queue.submit([encoder.finish()]);
        let slice = staging.slice(..size);
        let done = Arc::new(AtomicBool::new(false));
        let result = Arc::new(Mutex::new(None));
        {
            let (done, result) = (done.clone(), result.clone());
            slice.map_async(wgpu::MapMode::Read, move |r| {
                if let Ok(mut slot) = result.lock() {
                    *slot = Some(r);
                }
                done.store(true, Ordering::Release);
            });
        }
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        self.check()?;
        match result.lock().ok().and_then(|mut r| r.take()) {
            Some(Ok(())) => {}
            Some(Err(e)) => return Err(GpuError::Readback(e.to_string())),
            None => return Err(GpuError::Readback("the buffer was never mapped".into())),
        }
        let out = {
            let view = slice
                .get_mapped_range()
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            read(&view)
        };
        staging.unmap();
        Ok(out)
    }
}

/// One context per process, created on first use and replaced after a device loss.
#[derive(Debug, Default)]
pub struct SharedGpu {
    slot: Mutex<Option<Arc<GpuContext>>>,
}

impl SharedGpu {
    pub fn get(&self) -> Result<Arc<GpuContext>, GpuError> {
        let mut slot = self
            .slot
            .lock()
            .map_err(|_| GpuError::Validation("GPU context lock poisoned".into()))?;
        if let Some(ctx) = slot.as_ref()
            && !ctx.is_lost()
        {
            return Ok(ctx.clone());
        }
        let ctx = Arc::new(GpuContext::new()?);
        *slot = Some(ctx.clone());
        Ok(ctx)
    }
}

/// For tests of one pass in isolation.
#[cfg(test)]
impl GpuContext {
    /// Run `pipeline` once over `workgroups` workgroups (along x) with `resources` at bindings
    /// 0, 1, …, then hand the first `size` bytes of `output` (COPY_SRC) to `read`.
    pub(crate) fn run_once<T>(
        &self,
        pipeline: &wgpu::ComputePipeline,
        resources: &[wgpu::BindingResource],
        workgroups: u32,
        output: &wgpu::Buffer,
        size: u64,
        read: impl FnOnce(&[u8]) -> T,
    ) -> Result<T, GpuError> {
        let group = crate::shaders::pipeline_bind_group(&self.device, pipeline, "test", resources);
        let mut encoder = self.device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(workgroups, 1, 1);
        }
        self.queue.submit([encoder.finish()]);
        use wgpu::BufferUsages as U;
        let staging = self.buffer("staging", size, U::MAP_READ | U::COPY_DST);
        self.read_back(output, &staging, size, read)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_adapter_lists_the_available_ones() {
        match GpuContext::with_adapter(Some("no-such-gpu-anywhere")) {
            Err(GpuError::AdapterNotFound { available, .. }) => {
                assert!(available.contains("#0"), "{available}");
            }
            Err(GpuError::NoAdapter) => {} // a machine with no driver at all
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn limits_name_the_setting_to_lower() {
        let ctx = GpuContext::new().expect("a GPU adapter (lavapipe: mesa-vulkan-drivers)");
        let err = ctx
            .require("max_texture_dimension_2d", u64::MAX, "rsm_size")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("max_texture_dimension_2d") && err.contains("lower rsm_size"),
            "{err}"
        );
        assert!(
            ctx.require("max_texture_dimension_2d", 256, "rsm_size")
                .is_ok()
        );
        assert!(ctx.check().is_ok());
    }

    #[test]
    fn missing_features_name_what_needs_them() {
        let ctx = GpuContext::new().expect("a GPU adapter (lavapipe: mesa-vulkan-drivers)");
        let granted = ctx.device.features();
        // lavapipe (CI's adapter) has every optional feature, and is given them.
        if ctx.info.device_type == wgpu::DeviceType::Cpu {
            assert!(granted.contains(OPTIONAL_FEATURES), "{granted:?}");
        }
        assert!(ctx.require_features(granted, "anything").is_ok());
        let absent = wgpu::Features::all() - granted;
        let Some(feature) = absent.iter().next() else {
            return; // an adapter with every feature
        };
        let err = ctx
            .require_features(feature | granted, "the test pass")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(&format!("{feature:?}")) && err.contains("the test pass"),
            "{err}"
        );
    }
}
