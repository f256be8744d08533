//! The live depth reconstruction between the synchroniser and the scene: each depth frame is
//! checked (invalid depth never becomes geometry), filtered with the registered colour image as
//! guide, merged with the previous frames warped into the current view, and either handed on
//! for triangulation or — when too little of it is valid (too close, too bright, covered) —
//! replaced by the scene file's proxy of the room (`relight_recon::depth::ProxySwitch`).
//!
//! The filter and merge run on the GPU (`relight_engines::recon_gpu`) when the pipeline has a
//! GPU context, on the CPU (`relight-recon`, the GPU pass's test oracle) otherwise, or for a
//! frame the GPU failed on.

use std::sync::Arc;
use std::time::Instant;

use relight_core::camera::Pinhole;
use relight_core::{Image, Pose};
use relight_engines::PassTiming;
use relight_engines::gpu::GpuContext;
use relight_engines::recon_gpu::{DepthPass, DepthPassSettings};
use relight_recon::depth::{
    DepthMap, DepthRange, GeometrySource, GuidedFilterSettings, ProxySwitch, guided_filter,
};
use relight_recon::temporal::{MergeReport, TemporalMerge, TemporalSettings};

/// What the scene is built from this frame.
#[derive(Debug)]
pub enum DepthOutcome {
    /// The reconstructed depth (metres, f32; 0 = no surface), registered to colour.
    Depth(Image),
    /// Too little valid depth: use the proxy geometry.
    Proxy,
}

/// The reconstruction with its state across frames.
#[derive(Debug)]
pub struct DepthStage {
    camera: Pinhole,
    range: DepthRange,
    filter: GuidedFilterSettings,
    merge: TemporalMerge,
    switch: ProxySwitch,
    gpu: Option<(DepthPass, DepthPassSettings)>,
    /// The last frame's depth was merged with its history without a reset.
    surface_held: bool,
    /// The last frame's passes and their times (status: `depth.<pass>`).
    passes: Vec<PassTiming>,
}

impl DepthStage {
    /// For a Kinect-v1-like sensor whose registered depth has the intrinsics `camera`; on
    /// `gpu` when given.
    pub fn new(camera: Pinhole, gpu: Option<Arc<GpuContext>>) -> Self {
        let focal = camera.fx as f32;
        Self {
            camera,
            range: DepthRange::default(),
            filter: GuidedFilterSettings::kinect_v1(focal),
            merge: TemporalMerge::new(TemporalSettings::kinect_v1(focal)),
            switch: ProxySwitch::default(),
            gpu: gpu.map(|ctx| (DepthPass::new(ctx), DepthPassSettings::kinect_v1(focal))),
            surface_held: false,
            passes: Vec::new(),
        }
    }

    /// Whether the last [`process`](Self::process) merged its depth with the history without a
    /// reset: the temporal merge found the real surface unchanged.
    pub fn surface_held(&self) -> bool {
        self.surface_held
    }

    /// What the last [`process`](Self::process) ran and how long each part took: on the GPU,
    /// the upload, the GPU work with its read-back and the GPU passes by timestamp; on the
    /// CPU, the filter and the merge.
    pub fn passes(&self) -> &[PassTiming] {
        &self.passes
    }

    /// One depth frame, `colour` its registered colour image (the filter's guide; without one,
    /// or of another size, depth is merged unfiltered), the camera at `world_from_camera`.
    pub fn process(
        &mut self,
        depth: &Image,
        colour: Option<&Image>,
        world_from_camera: &Pose,
    ) -> DepthOutcome {
        self.surface_held = false;
        self.passes.clear();
        let (map, census) = match DepthMap::from_image_with_census(depth, self.range) {
            Ok(parsed) => parsed,
            Err(error) => {
                tracing::debug!(%error, "depth frame not usable");
                self.switch.update_fraction(0.0);
                return DepthOutcome::Proxy;
            }
        };
        if self.switch.update(&census) == GeometrySource::Proxy {
            return DepthOutcome::Proxy;
        }
        let guide = colour.filter(|c| c.width() == map.width && c.height() == map.height);
        if let (Some((pass, settings)), Some(guide)) = (&mut self.gpu, guide) {
            match pass.run(&map, guide, &self.camera, world_from_camera, settings) {
                Ok(frame) => {
                    self.surface_held = frame.merge.as_ref().is_some_and(surface_unchanged);
                    self.passes.clone_from(&frame.timings);
                    return DepthOutcome::Depth(frame.depth.to_image());
                }
                Err(error) => {
                    tracing::warn!(%error, "GPU depth pass failed: this frame on the CPU")
                }
            }
        }
        let started = Instant::now();
        let filtered = guide
            .and_then(|guide| {
                guided_filter(&map, guide, &self.filter)
                    .inspect_err(|error| tracing::debug!(%error, "depth not filtered"))
                    .ok()
            })
            .unwrap_or(map);
        let filtered_at = Instant::now();
        let merged = self.merge.merge(&filtered, &self.camera, world_from_camera);
        self.passes.extend([
            PassTiming {
                pass: "cpu filter",
                ms: (filtered_at - started).as_secs_f64() * 1e3,
            },
            PassTiming {
                pass: "cpu merge",
                ms: filtered_at.elapsed().as_secs_f64() * 1e3,
            },
        ]);
        match merged {
            Ok(merged) => {
                self.surface_held = surface_unchanged(self.merge.report());
                DepthOutcome::Depth(merged.to_image())
            }
            Err(error) => {
                tracing::debug!(%error, "depth not merged");
                DepthOutcome::Depth(filtered.to_image())
            }
        }
    }
}

/// Share of the pixels compared with the history that may disagree with it while the real
/// surface still counts as unchanged: a correctly tracked camera has under 1 % (edges, noise;
/// [`TemporalSettings::kinect_v1`]), so more means something in view moved, even where too
/// little moved for the merge to reset.
const MAX_CHANGED_SHARE: f32 = 0.03;

/// Whether a merge found the real surface unchanged: no reset, and at most
/// [`MAX_CHANGED_SHARE`] of the compared pixels rejected.
fn surface_unchanged(report: &MergeReport) -> bool {
    let compared = report.merged + report.rejected;
    report.reset.is_none()
        && compared > 0
        && report.rejected as f32 <= MAX_CHANGED_SHARE * compared as f32
}
