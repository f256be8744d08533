//! The light probe's estimate, frame by frame: collect one bracket of exposures, merge it to HDR
//! ([`crate::hdr::merge`], Robertson), resample it into a world-direction environment map through
//! the calibrated lens and pose ([`crate::envmap::ProbeResampler`], made once: the lens and its
//! pose are fixed), split it into lights ([`crate::median_cut::extract_lights`]) and project it
//! to SH9 ([`crate::irradiance::project_sh9`]).
//!
//! Brackets: the probe cycles through its exposures, one per frame. The newest frame of each
//! exposure is kept. The cycle's length is learned from the stream: it is the number of
//! exposures seen when one comes round again (and is learned anew when an exposure never seen
//! appears, e.g. after the exposure settings change). A bracket is complete when every exposure
//! of the cycle has a frame newer than the last estimate, so an estimate follows each full cycle
//! and no frame enters two estimates. Frames older than [`ProbeSettings::max_age_ns`] are dropped (a stalled exposure
//! must not hold a stale sky in the bracket). A change of image size starts over.

use std::sync::Arc;

use glam::Vec3;
use relight_core::camera::{CameraModel, KannalaBrandt};
use relight_core::light::Light;
use relight_core::rig::RigCalibration;
use relight_core::scene::EnvironmentMap;
use relight_core::sh::Sh9Rgb;
use relight_core::{Frame, Pose, ProbeImage, Timestamp};

use crate::envmap::{EnvMapError, EnvMapSettings, ProbeResampler, texel_direction};
use crate::hdr::{HdrError, Response, merge};
use crate::irradiance::project_sh9;
use crate::median_cut::{MedianCutSettings, extract_lights};
use crate::vignetting::Vignetting;

/// Why the probe cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProbeError {
    #[error("the rig calibration has no Kannala–Brandt probe model")]
    NoProbeModel,
    #[error("the probe's response: {0}")]
    Response(#[from] HdrError),
    #[error("the probe's environment map: {0}")]
    EnvMap(#[from] EnvMapError),
}

/// How the estimate is made.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeSettings {
    pub envmap: EnvMapSettings,
    pub lights: MedianCutSettings,
    /// Radiance, W/(m²·sr), per unit of merged HDR value (linearised response per second of
    /// exposure): the probe's absolute photometric calibration
    /// ([`RigCalibration::probe_radiance_scale`]).
    pub radiance_scale: f32,
    /// Frames older than this (device clock, relative to the newest) leave the bracket.
    pub max_age_ns: u64,
    /// Angular radius, degrees, masked out of the map around each tracked light
    /// ([`ProbeLighting::track_light`]): the bulb's disc, the map's resampling blur
    /// (a texel of the default 128 × 64 map is 2.8°) and the light's motion between two of its
    /// reports.
    pub tracked_light_mask_deg: f32,
}

impl Default for ProbeSettings {
    fn default() -> Self {
        Self {
            envmap: EnvMapSettings {
                width: 128,
                height: 64,
                ..EnvMapSettings::default()
            },
            lights: MedianCutSettings::default(),
            radiance_scale: 1.0,
            max_age_ns: 2_000_000_000,
            tracked_light_mask_deg: 8.0,
        }
    }
}

/// One estimate from one bracket.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbeEstimate {
    /// Timestamp of the bracket's newest frame.
    pub stamp: Timestamp,
    /// World-direction radiance, W/(m²·sr); directions the probe does not see are black.
    pub environment: Arc<EnvironmentMap>,
    /// The map's radiance as L2 SH.
    pub sh9: Sh9Rgb,
    /// One directional light per median-cut region, brightest first.
    pub lights: Vec<Light>,
    /// Exposures merged.
    pub exposures: usize,
    /// Radiance in W/(m²·sr); `false`: relative units (no radiance scale in the calibration).
    pub absolute: bool,
}

/// Turns probe frames into estimates (see the module docs).
#[derive(Debug)]
pub struct ProbeLighting {
    lens: KannalaBrandt,
    world_from_probe: Pose,
    response: Response,
    settings: ProbeSettings,
    /// Newest frame per exposure, and whether it arrived after the last estimate.
    bracket: Vec<(Arc<Frame<ProbeImage>>, bool)>,
    /// Exposures per cycle, once one has come round.
    cycle: Option<usize>,
    vignetting: Option<Vignetting>,
    /// Where the tracked lights were (host time, ns; world position) over the last brackets.
    tracked: Vec<(u64, Vec3)>,
    /// The lens and pose's resampling into the map, made on the first estimate.
    resampler: std::sync::OnceLock<ProbeResampler>,
}

/// How far (host time) around a bracket's frames a tracked light's report still masks: a lamp
/// reports a few times a second.
const TRACKED_LIGHT_WINDOW_NS: u64 = 200_000_000;

impl ProbeLighting {
    /// From the rig's calibration: its Kannala–Brandt probe, the probe's pose and inverse
    /// response (a linear response when the calibration has none), and its radiance scale.
    pub fn new(rig: &RigCalibration, mut settings: ProbeSettings) -> Result<Self, ProbeError> {
        let Some(CameraModel::KannalaBrandt(lens)) = rig.probe else {
            return Err(ProbeError::NoProbeModel);
        };
        let response = if rig.probe_response.is_empty() {
            Response::linear()
        } else {
            Response::from_calibration(rig)?
        };
        settings.radiance_scale = rig.probe_radiance_scale;
        let vignetting = (!rig.probe_vignetting.is_empty())
            .then(|| Vignetting::new(&CameraModel::KannalaBrandt(lens), &rig.probe_vignetting));
        Ok(Self {
            lens,
            world_from_probe: rig.world_from_probe,
            response,
            settings,
            bracket: Vec::new(),
            cycle: None,
            vignetting,
            tracked: Vec::new(),
            resampler: std::sync::OnceLock::new(),
        })
    }

    /// Whether the estimate is in W/(m²·sr) (the rig calibration has the probe's radiance
    /// scale) or in relative units.
    pub fn is_absolute(&self) -> bool {
        self.settings.radiance_scale != 1.0
    }

    /// A light the rig tracks itself (the pocket lamp) was at `position_in_world` at host time
    /// `host_ns`. Its disc is masked out of the environment before the median cut and SH9, so
    /// that it is counted once: as the tracked light, not also as a probe light.
    pub fn track_light(&mut self, host_ns: u64, position_in_world: Vec3) {
        if !position_in_world.is_finite() {
            return;
        }
        let horizon = host_ns.saturating_sub(self.settings.max_age_ns + TRACKED_LIGHT_WINDOW_NS);
        self.tracked.retain(|(t, _)| *t >= horizon);
        self.tracked.push((host_ns, position_in_world));
    }

    /// Take one probe frame; returns an estimate when it completes a bracket.
    pub fn push(
        &mut self,
        frame: &Arc<Frame<ProbeImage>>,
    ) -> Result<Option<ProbeEstimate>, ProbeError> {
        let image = &frame.payload.image;
        let newest = frame.stamp.device_ns;
        let max_age = self.settings.max_age_ns;
        let before = self.bracket.len();
        self.bracket.retain(|(f, _)| {
            f.payload.image.width() == image.width()
                && f.payload.image.height() == image.height()
                && newest.saturating_sub(f.stamp.device_ns) <= max_age
        });
        if self.bracket.len() != before {
            self.cycle = None;
        }
        match self
            .bracket
            .iter_mut()
            .find(|(f, _)| f.payload.exposure_us == frame.payload.exposure_us)
        {
            Some(slot) => {
                *slot = (frame.clone(), true);
                self.cycle.get_or_insert(self.bracket.len());
            }
            None => {
                self.bracket.push((frame.clone(), true));
                self.cycle = None;
            }
        }
        let complete = self
            .cycle
            .is_some_and(|n| n >= 2 && self.bracket.len() >= n);
        if !complete || !self.bracket.iter().all(|(_, fresh)| *fresh) {
            return Ok(None);
        }
        for (_, fresh) in &mut self.bracket {
            *fresh = false;
        }
        self.estimate().map(Some)
    }

    /// Black out the texels within [`ProbeSettings::tracked_light_mask_deg`] of where each
    /// tracked light was while the bracket was exposed: the reports from the last one before
    /// the bracket's first frame to the first one after its last, and the path between
    /// consecutive reports (a lamp carried through the bracket smears its disc along it).
    fn mask_tracked_lights(&self, environment: &mut EnvironmentMap) {
        let times = self.bracket.iter().map(|(f, _)| f.stamp.host_ns);
        let (Some(first), Some(last)) = (times.clone().min(), times.max()) else {
            return;
        };
        let mut reports: Vec<(u64, Vec3)> = self.tracked.clone();
        reports.sort_by_key(|(t, _)| *t);
        let start = reports.iter().rposition(|(t, _)| *t <= first).unwrap_or(0);
        let end = reports
            .iter()
            .position(|(t, _)| *t >= last)
            .unwrap_or(reports.len().saturating_sub(1));
        let Some(window) = reports.get(start..=end) else {
            return;
        };
        let mut window = window.to_vec();
        // The report that follows the bracket's last frame may not have come yet: carry the
        // light on at its last velocity (a lamp reports a few times a second).
        if let [.., (t0, p0), (t1, p1)] = window[..]
            && t1 < last
            && t1 > t0
            && last - t1 <= 2 * (t1 - t0)
        {
            let k = (last - t1) as f32 / (t1 - t0) as f32;
            window.push((last, p1 + (p1 - p0) * k));
        }
        let near_the_bracket =
            |t: u64| t + TRACKED_LIGHT_WINDOW_NS >= first && t <= last + TRACKED_LIGHT_WINDOW_NS;
        if !window.iter().any(|(t, _)| near_the_bracket(*t)) {
            return;
        }
        let origin = self.world_from_probe.translation;
        let mask_rad = self.settings.tracked_light_mask_deg.to_radians();
        let mut directions: Vec<Vec3> = Vec::new();
        for pair in window.windows(2) {
            let (a, b) = (pair[0].1 - origin, pair[1].1 - origin);
            let (Some(a), Some(b)) = (a.try_normalize(), b.try_normalize()) else {
                continue;
            };
            let steps = (a.angle_between(b) / (0.5 * mask_rad)).ceil().max(1.0) as usize;
            directions.extend(
                (0..=steps).filter_map(|k| a.lerp(b, k as f32 / steps as f32).try_normalize()),
            );
        }
        directions.extend(
            window
                .iter()
                .filter_map(|(_, p)| (*p - origin).try_normalize()),
        );
        let cos_mask = mask_rad.cos();
        let (w, h) = (environment.width, environment.height);
        for y in 0..h {
            for x in 0..w {
                let dir = texel_direction(w, h, x, y);
                if directions.iter().any(|d| d.dot(dir) >= cos_mask) {
                    environment.radiance[(y * w + x) as usize] = Vec3::ZERO;
                }
            }
        }
    }

    fn estimate(&self) -> Result<ProbeEstimate, ProbeError> {
        let frames: Vec<&ProbeImage> = self.bracket.iter().map(|(f, _)| &f.payload).collect();
        let mut hdr = merge(&frames, &self.response)?;
        if let Some(vignetting) = &self.vignetting {
            vignetting.correct(&mut hdr);
        }
        let scale = self.settings.radiance_scale;
        if scale != 1.0 && scale.is_finite() && scale > 0.0 {
            for l in &mut hdr.radiance {
                *l *= scale;
            }
        }
        let resampler = match self.resampler.get() {
            Some(resampler) => resampler,
            None => {
                let made =
                    ProbeResampler::new(&self.lens, &self.world_from_probe, &self.settings.envmap)?;
                self.resampler.get_or_init(|| made)
            }
        };
        let mut environment = resampler.resample(&hdr)?.map;
        self.mask_tracked_lights(&mut environment);
        let lights = extract_lights(&environment, &self.settings.lights)?
            .iter()
            .map(|r| r.to_light())
            .collect();
        let sh9 = project_sh9(&environment)?;
        let stamp = self
            .bracket
            .iter()
            .map(|(f, _)| f.stamp)
            .max()
            .unwrap_or_default();
        Ok(ProbeEstimate {
            stamp,
            absolute: self.is_absolute(),
            environment: Arc::new(environment),
            sh9,
            lights,
            exposures: frames.len(),
        })
    }
}
