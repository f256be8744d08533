//! The live depth reconstruction between the synchroniser and the scene: each depth frame is
//! checked (invalid depth never becomes geometry), filtered with the registered colour image as
//! guide, merged with the previous frames warped into the current view, and either handed on
//! for triangulation or — when too little of it is valid (too close, too bright, covered) —
//! replaced by the scene file's proxy of the room (`relight_recon::depth::ProxySwitch`).

use relight_core::camera::Pinhole;
use relight_core::{Image, Pose};
use relight_recon::depth::{
    DepthMap, DepthRange, GeometrySource, GuidedFilterSettings, ProxySwitch, guided_filter,
};
use relight_recon::temporal::{TemporalMerge, TemporalSettings};

/// What the scene is built from this frame.
#[derive(Debug)]
pub enum DepthOutcome {
    /// The reconstructed depth (metres, f32; 0 = no surface), registered to colour.
    Depth(Image),
    /// Too little valid depth: use the proxy geometry.
    Proxy,
}

/// The CPU reconstruction (`relight-recon`) with its state across frames.
#[derive(Debug)]
pub struct DepthStage {
    camera: Pinhole,
    range: DepthRange,
    filter: GuidedFilterSettings,
    merge: TemporalMerge,
    switch: ProxySwitch,
}

impl DepthStage {
    /// For a Kinect-v1-like sensor whose registered depth has the intrinsics `camera`.
    pub fn new(camera: Pinhole) -> Self {
        let focal = camera.fx as f32;
        Self {
            camera,
            range: DepthRange::default(),
            filter: GuidedFilterSettings::kinect_v1(focal),
            merge: TemporalMerge::new(TemporalSettings::kinect_v1(focal)),
            switch: ProxySwitch::default(),
        }
    }

    /// One depth frame, `colour` its registered colour image (the filter's guide; without one,
    /// or of another size, depth is merged unfiltered), the camera at `world_from_camera`.
    pub fn process(
        &mut self,
        depth: &Image,
        colour: Option<&Image>,
        world_from_camera: &Pose,
    ) -> DepthOutcome {
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
        let filtered = colour
            .filter(|c| c.width() == map.width && c.height() == map.height)
            .and_then(|guide| {
                guided_filter(&map, guide, &self.filter)
                    .inspect_err(|error| tracing::debug!(%error, "depth not filtered"))
                    .ok()
            })
            .unwrap_or(map);
        match self.merge.merge(&filtered, &self.camera, world_from_camera) {
            Ok(merged) => DepthOutcome::Depth(merged.to_image()),
            Err(error) => {
                tracing::debug!(%error, "depth not merged");
                DepthOutcome::Depth(filtered.to_image())
            }
        }
    }
}
