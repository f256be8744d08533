//! `relightd score`: the live loop measured end to end against a simulated recording's truth.
//!
//! The recording's messages go, in log order, through the same synchroniser settings and the same
//! [`LiveFrames`] the render thread uses (tracking, depth filter and merge, live mesh, lighting
//! estimate), then through the engine. On every frame set that has ground truth the scorer
//! renders the truth with the reference path tracer (the scene's real meshes and virtual object
//! at the true camera pose, under the true lights) and measures each stage's output against it.
//!
//! The same engine also renders the same frames from *oracle* inputs (true pose, the scene's true
//! geometry and materials, the true lights, the same camera image), so the live error splits
//! into what the engine's method costs and what the live inputs add.
//!
//! The true composite follows the engines' own compositing (DLPV Algorithm 1): the camera image
//! plus the true Δ on real pixels, the true L^ρ on virtual pixels, in linear sRGB clipped to
//! [0, 1] as an 8-bit composite is. The colour camera's own response and exposure are not part
//! of it (no engine models them yet).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context as _, bail};
use glam::Vec3;
use relight_core::camera::{CameraModel, optical_from_gl};
use relight_core::light::Light;
use relight_core::recording::RecordingReader;
use relight_core::recording::truth::{TruthKind, TruthMessage, TruthState};
use relight_core::scene::{Scene, box_corners};
use relight_core::sync::{FrameSet, Synchronizer};
use relight_core::{Image, Pose, StreamKind};
use relight_engines::live_scene::RealGeometry;
use relight_engines::offline::{self, Sampling, Transport, delta_pixels, reference, srgb_image};
use relight_engines::reference::ReferenceImages;
use relight_engines::reference_cache::ReferenceCache;
use relight_engines::{EngineRegistry, RelitFrame, SceneFrame};
use serde::Serialize;
use serde_json::{Map, Value};

use crate::config::Config;
use crate::control::lights::LightsBoard;
use crate::pipeline::live_frame::LiveFrames;
use crate::pipeline::reconstruction::DepthOutcome;
use crate::pipeline::sources::{core_sync_config, expect_only_recorded_streams};
use crate::sinks::png_out::write_png;

/// What to score.
#[derive(Debug, Clone)]
pub struct ScoreSettings {
    pub recording: PathBuf,
    pub scene: PathBuf,
    pub engine: String,
    pub params: Map<String, Value>,
    /// Samples per pixel of the truth's reference renders.
    pub reference_spp: u32,
    /// Where truth renders are kept between runs (a [`ReferenceCache`] keyed by the scene's
    /// files, the frame's true pose and lights, and the samples); `None`: always render.
    pub reference_cache: Option<PathBuf>,
    /// Write each truth frame's live, oracle and true composites here.
    pub out: Option<PathBuf>,
    /// The rest of the live path (`[scene]`, `[tracking]`, `[sync]`); source and engine are
    /// ignored.
    pub config: Config,
    /// Probe and albedo estimates on threads of their own, as in the daemon (else inline, in
    /// frame order, so the scores do not depend on thread timing).
    pub threads: bool,
}

/// The measures of one truth frame. `None` where a measure does not apply (untracked: no pose).
#[derive(Debug, Clone, Serialize)]
pub struct FrameScore {
    /// Frame set number in the replay (0 = first).
    pub seq: u64,
    /// `fixed`, `tracked`, `held` or `untracked`.
    pub tracking: String,
    pub pose_error_mm: Option<f64>,
    pub pose_error_deg: Option<f64>,
    pub object_reprojection_px: Option<f64>,
    pub depth_rmse_mm: Option<f64>,
    pub albedo_rel_error: Option<f64>,
    pub light_direction_error_deg: Option<f64>,
    pub light_irradiance_ratio: Option<f64>,
    pub composite_rel_l2_real: f64,
    pub composite_rel_l2_virtual: f64,
    pub delta_rel_l2: f64,
    /// `delta_rel_l2` over the object's true shadow and over its true bleeding alone (the real
    /// pixels where the true Δ is significantly negative or positive,
    /// [`offline::region_errors`]); `None` where the truth has no such pixel.
    pub delta_rel_l2_shadow: Option<f64>,
    pub delta_rel_l2_bleeding: Option<f64>,
    pub delta_rel_l2_oracle: f64,
    pub composite_rel_l2_real_oracle: f64,
    /// The truth's own sampling noise in the metric of `delta_rel_l2`
    /// ([`offline::reference_noise`]): against a truth of `--reference-spp` samples an engine
    /// with true error e reads about √(e² + noise²), so an error near this is noise. Path-traced
    /// noise is heavy-tailed, so at few samples this reads low (desk_box at 80 × 60: 0.51 at 16
    /// spp, where such a truth differs from a converged one by 0.60; within 5 % from 64 spp).
    pub delta_truth_noise: f64,
    /// ‖Δ_true‖ / ‖true composite‖ over real pixels: how much of the picture Δ is, which bounds
    /// how far a relative error of Δ can move the composite.
    pub delta_share_real: f64,
}

/// Median and 95th percentile of one measure over the frames where it applies.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Summary {
    pub median: f64,
    pub p95: f64,
    pub frames: usize,
}

/// The whole run.
#[derive(Debug, Clone, Serialize)]
pub struct ScoreReport {
    pub recording: String,
    pub engine: String,
    /// Frame sets replayed, and those the tracker had a pose for.
    pub frames: usize,
    pub tracked_frames: usize,
    /// Truth frames scored.
    pub scored_frames: usize,
    pub measures: BTreeMap<&'static str, Summary>,
    /// Mean milliseconds per frame set of each live stage.
    pub timings_ms: BTreeMap<String, f64>,
    pub per_frame: Vec<FrameScore>,
    /// The engine's own report after the last frame ([`relight_engines::Engine::status`]:
    /// `auto`'s choice); `None` for an engine without one.
    pub engine_status: Option<Value>,
}

/// The measures in report order (the `--json` keys).
pub const MEASURES: [&str; 15] = [
    "pose_error_mm",
    "pose_error_deg",
    "object_reprojection_px",
    "depth_rmse_mm",
    "albedo_rel_error",
    "light_direction_error_deg",
    "light_irradiance_ratio",
    "composite_rel_l2_real",
    "composite_rel_l2_virtual",
    "delta_rel_l2",
    "delta_rel_l2_shadow",
    "delta_rel_l2_bleeding",
    "delta_rel_l2_oracle",
    "composite_rel_l2_real_oracle",
    "delta_truth_noise",
];

impl FrameScore {
    fn measure(&self, name: &str) -> Option<f64> {
        match name {
            "pose_error_mm" => self.pose_error_mm,
            "pose_error_deg" => self.pose_error_deg,
            "object_reprojection_px" => self.object_reprojection_px,
            "depth_rmse_mm" => self.depth_rmse_mm,
            "albedo_rel_error" => self.albedo_rel_error,
            "light_direction_error_deg" => self.light_direction_error_deg,
            "light_irradiance_ratio" => self.light_irradiance_ratio,
            "composite_rel_l2_real" => Some(self.composite_rel_l2_real),
            "composite_rel_l2_virtual" => Some(self.composite_rel_l2_virtual),
            "delta_rel_l2" => Some(self.delta_rel_l2),
            "delta_rel_l2_shadow" => self.delta_rel_l2_shadow,
            "delta_rel_l2_bleeding" => self.delta_rel_l2_bleeding,
            "delta_rel_l2_oracle" => Some(self.delta_rel_l2_oracle),
            "composite_rel_l2_real_oracle" => Some(self.composite_rel_l2_real_oracle),
            "delta_truth_noise" => Some(self.delta_truth_noise),
            _ => None,
        }
        .filter(|v| v.is_finite())
    }
}

/// The reference render of `true_scene` (the scene at a frame's true pose under its true lights)
/// at the scene camera's size, read from the cache where one was kept.
fn truth_reference(
    settings: &ScoreSettings,
    true_scene: &Scene,
) -> anyhow::Result<ReferenceImages> {
    let (width, height) = (true_scene.camera.width, true_scene.camera.height);
    let spp = settings.reference_spp;
    let cache = settings.reference_cache.as_ref().and_then(|dir| {
        let view = format!(
            "score truth: {spp} spp, camera {:?}, lights {:?}",
            true_scene.camera, true_scene.lights
        );
        let key = ReferenceCache::key_of_view(
            &settings.scene,
            width,
            height,
            Sampling::Centre,
            Transport::Full,
            &view,
        );
        match key {
            Ok(key) => Some((ReferenceCache::new(dir), key)),
            Err(error) => {
                tracing::warn!(%error, "the truth is not cached: the scene's files do not read");
                None
            }
        }
    });
    if let Some(images) = cache.as_ref().and_then(|(cache, key)| cache.load(*key)) {
        return Ok(images);
    }
    let images = reference(true_scene, width, height, spp)?;
    if let Some((cache, key)) = cache
        && let Err(error) = cache.store(key, &images)
    {
        tracing::warn!(%error, "truth frame not cached");
    }
    Ok(images)
}

/// Nearest-rank quantile of sorted `values`.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (q * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

fn summarise(frames: &[FrameScore], name: &str) -> Summary {
    let mut values: Vec<f64> = frames.iter().filter_map(|f| f.measure(name)).collect();
    values.sort_by(f64::total_cmp);
    Summary {
        median: quantile(&values, 0.5),
        p95: quantile(&values, 0.95),
        frames: values.len(),
    }
}

/// The truth of one frame, gathered from its messages.
#[derive(Default)]
struct Truth {
    state: Option<TruthState>,
    depth: Option<Image>,
    albedo: Option<Image>,
}

/// Replay `settings.recording` through the live path and score every truth frame;
/// `progress(done, total)` after each.
pub fn run(
    settings: &ScoreSettings,
    mut progress: impl FnMut(usize, usize),
) -> anyhow::Result<ScoreReport> {
    let reader = RecordingReader::open(&settings.recording)
        .with_context(|| format!("reading {}", settings.recording.display()))?;
    let calibration = reader.meta().calibration.clone();
    let camera = match calibration.as_ref().and_then(|c| c.color.or(c.depth)) {
        Some(CameraModel::Pinhole(p)) => p,
        _ => bail!("the recording's calibration has no pinhole colour camera"),
    };
    let messages: Vec<_> = reader
        .messages()
        .collect::<Result<_, _>>()
        .context("reading the recording's messages")?;
    let mut truths: BTreeMap<u64, Truth> = BTreeMap::new();
    for message in reader.truth() {
        let message = message.context("reading the recording's truth")?;
        let entry = truths.entry(message.stamp().host_ns).or_default();
        match message {
            TruthMessage::State(frame) => entry.state = Some(frame.payload),
            TruthMessage::Image(TruthKind::Depth, frame) => entry.depth = Some(frame.payload),
            TruthMessage::Image(TruthKind::Albedo, frame) => entry.albedo = Some(frame.payload),
            TruthMessage::Image(..) => {}
        }
    }
    let total = truths.values().filter(|t| t.state.is_some()).count();
    if total == 0 {
        bail!(
            "{} has no ground truth (record it with `relightd simulate`)",
            settings.recording.display()
        );
    }

    let mut config = settings.config.clone();
    config.scene.dir = Some(settings.scene.clone());
    config.engine.name.clone_from(&settings.engine);
    let registry = EngineRegistry::new();
    let mut live = LiveFrames::new(&config, calibration.as_ref(), &registry)?;
    if settings.threads {
        live.probe_on_own_thread()?;
        live.albedo_on_own_thread()?;
    }
    let mut engine = registry.build(&settings.engine, &settings.params)?.engine;
    let mut oracle_engine = registry.build(&settings.engine, &settings.params)?.engine;
    let mut passthrough = registry.build("passthrough", &Map::new())?.engine;
    let mut oracle_scene = Scene::load(&settings.scene)?;
    oracle_scene.camera.width = camera.width;
    oracle_scene.camera.height = camera.height;
    oracle_scene.camera.yfov_rad = camera.yfov_rad() as f32;
    let virtual_corners: Vec<Vec3> = oracle_scene
        .virtual_bounds()
        .map(box_corners)
        .map_or_else(Vec::new, Vec::from);
    if config.scene.real != RealGeometry::Depth {
        tracing::warn!(
            "[scene] real = \"scene\": the live surface is the scene file's, not measured"
        );
    }

    let mut sync = core_sync_config(&config.sync);
    let mut recorded: Vec<StreamKind> = messages.iter().map(|m| m.kind()).collect();
    recorded.sort();
    recorded.dedup();
    expect_only_recorded_streams(&mut sync, &recorded, &settings.recording);
    let mut synchronizer = Synchronizer::new(sync).context("[sync]")?;
    let board = LightsBoard::new();
    let mut relit = RelitFrame::default();
    let mut oracle_relit = RelitFrame::default();
    let mut stage_ms: BTreeMap<String, (f64, usize)> = BTreeMap::new();
    let mut add_ms = |name: &str, ms: f64| {
        let entry = stage_ms.entry(name.to_owned()).or_insert((0.0, 0));
        entry.0 += ms;
        entry.1 += 1;
    };
    let (mut frames, mut tracked) = (0usize, 0usize);
    let mut per_frame = Vec::new();
    let mut score_set = |set: FrameSet,
                         live: &mut LiveFrames,
                         add_ms: &mut dyn FnMut(&str, f64)|
     -> anyhow::Result<()> {
        let seq = frames as u64;
        frames += 1;
        let frame = live.frame(&set, seq, &board);
        for (name, ms) in frame.timings.named() {
            add_ms(name, ms);
        }
        let start = Instant::now();
        let used = if frame.tracking.is_usable() {
            tracked += 1;
            &mut engine
        } else {
            &mut passthrough
        };
        if let Err(error) = used.render(&frame.scene, &mut relit) {
            tracing::warn!(%error, seq, "frame not rendered");
            relit = RelitFrame::default();
        }
        add_ms("render", start.elapsed().as_secs_f64() * 1e3);
        let Some(truth) = truths.get(&set.stamp.host_ns) else {
            return Ok(());
        };
        let Some(state) = &truth.state else {
            return Ok(());
        };
        let Some(color) = set.color.as_ref() else {
            return Ok(());
        };
        let mut true_scene = oracle_scene.clone();
        true_scene.camera.world_from_camera = state.world_from_camera;
        true_scene.lights.clone_from(&state.lights);
        let start = Instant::now();
        let truth_images = truth_reference(settings, &true_scene)?;
        add_ms("truth reference", start.elapsed().as_secs_f64() * 1e3);
        let true_scene = Arc::new(true_scene);
        let oracle_frame = SceneFrame {
            scene: Some(true_scene.clone()),
            ..frame.scene.clone()
        };
        if let Err(error) = oracle_engine.render(&oracle_frame, &mut oracle_relit) {
            tracing::warn!(%error, seq, "oracle frame not rendered");
            oracle_relit = RelitFrame::default();
        }

        let background: Vec<Vec3> = offline::composite_pixels(&color.payload);
        let mask = &truth_images.virtual_mask;
        let true_composite: Vec<Vec3> = background
            .iter()
            .zip(&truth_images.delta)
            .zip(&truth_images.l_rho)
            .zip(mask)
            .map(|(((b, d), l), v)| if *v { *l } else { *b + *d })
            .map(|c| c.clamp(Vec3::ZERO, Vec3::ONE))
            .collect();
        let composite = offline::composite_pixels(&relit.composite);
        let oracle_composite = offline::composite_pixels(&oracle_relit.composite);
        let delta = delta_or_zero(&relit.delta, mask.len());
        let oracle_delta = delta_or_zero(&oracle_relit.delta, mask.len());
        let real: Vec<bool> = mask.iter().map(|v| !v).collect();
        let regions = offline::region_errors(&delta, &truth_images);

        let pose = frame.tracking.world_from_camera;
        let pose_error = pose.map(|p| pose_difference(&p, &state.world_from_camera));
        let reprojection = pose
            .and_then(|p| reprojection_px(&camera, &virtual_corners, &p, &state.world_from_camera));
        let depth_rmse_mm = match (&frame.depth, &truth.depth) {
            (Some(DepthOutcome::Depth(estimate)), Some(truth)) => depth_rmse_m(estimate, truth),
            _ => None,
        }
        .map(|m| m * 1e3);
        let albedo_rel_error = match (&truth.albedo, &frame.scene.scene, pose) {
            (Some(albedo), Some(scene), Some(pose)) => {
                albedo_error(scene, &camera, &pose, albedo, truth.depth.as_ref())
            }
            _ => None,
        };
        let (light_direction_error_deg, light_irradiance_ratio) = board
            .latest()
            .zip(state.world_from_probe)
            .and_then(|(estimate, world_from_probe)| {
                main_light_error(
                    &estimate.lights,
                    &state.lights,
                    world_from_probe.translation,
                )
            })
            .map_or((None, None), |(deg, ratio)| (Some(deg), Some(ratio)));
        let score = FrameScore {
            seq,
            tracking: frame.tracking.state.name().to_owned(),
            pose_error_mm: pose_error.map(|(mm, _)| mm),
            pose_error_deg: pose_error.map(|(_, deg)| deg),
            object_reprojection_px: reprojection,
            depth_rmse_mm,
            albedo_rel_error,
            light_direction_error_deg,
            light_irradiance_ratio,
            composite_rel_l2_real: relative_l2(&composite, &true_composite, &real),
            composite_rel_l2_virtual: relative_l2(&composite, &true_composite, mask),
            delta_rel_l2: relative_l2(&delta, &truth_images.delta, &real),
            delta_rel_l2_shadow: regions.shadow_relative_l2,
            delta_rel_l2_bleeding: regions.bleeding_relative_l2,
            delta_rel_l2_oracle: relative_l2(&oracle_delta, &truth_images.delta, &real),
            composite_rel_l2_real_oracle: relative_l2(&oracle_composite, &true_composite, &real),
            delta_truth_noise: offline::reference_noise(&truth_images),
            delta_share_real: l2(&truth_images.delta, &real) / l2(&true_composite, &real),
        };
        if let Some(dir) = &settings.out {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            let n = per_frame.len();
            write_png(&dir.join(format!("{n:04}_live.png")), &relit.composite)?;
            write_png(
                &dir.join(format!("{n:04}_oracle.png")),
                &oracle_relit.composite,
            )?;
            write_png(
                &dir.join(format!("{n:04}_truth.png")),
                &srgb_image(camera.width, camera.height, &true_composite),
            )?;
        }
        per_frame.push(score);
        progress(per_frame.len(), total);
        Ok(())
    };

    let mut data_clock_ns = 0u64;
    for message in messages {
        data_clock_ns = data_clock_ns.max(message.stamp().host_ns);
        match &message {
            relight_core::StreamMessage::Probe(frame) => {
                if let Some(ms) = live.probe_frame(frame) {
                    add_ms("probe", ms);
                }
            }
            relight_core::StreamMessage::Lamp(frame) => live.lamp_report(frame),
            _ => {}
        }
        synchronizer.push(message);
        while let Some(set) = synchronizer.pop_ready(data_clock_ns) {
            score_set(set, &mut live, &mut add_ms)?;
        }
    }
    for set in synchronizer.flush() {
        score_set(set, &mut live, &mut add_ms)?;
    }
    let engine_status = engine.status();
    let measures = MEASURES
        .iter()
        .map(|name| (*name, summarise(&per_frame, name)))
        .collect();
    Ok(ScoreReport {
        recording: settings.recording.display().to_string(),
        engine: settings.engine.clone(),
        frames,
        tracked_frames: tracked,
        scored_frames: per_frame.len(),
        measures,
        timings_ms: stage_ms
            .into_iter()
            .map(|(name, (sum, n))| (name, sum / n.max(1) as f64))
            .collect(),
        per_frame,
        engine_status,
    })
}

impl ScoreReport {
    /// The `--json` document: one object per measure with `median` and `p95`, beside `frames`,
    /// `tracked_frames`, `engine` and `recording`.
    pub fn to_json(&self) -> Value {
        let mut out = Map::new();
        for (name, summary) in &self.measures {
            out.insert(
                (*name).to_owned(),
                serde_json::json!({ "median": finite(summary.median), "p95": finite(summary.p95), "frames": summary.frames }),
            );
        }
        out.insert("frames".into(), self.frames.into());
        out.insert("tracked_frames".into(), self.tracked_frames.into());
        out.insert("scored_frames".into(), self.scored_frames.into());
        out.insert("engine".into(), self.engine.clone().into());
        out.insert("recording".into(), self.recording.clone().into());
        out.insert(
            "timings_ms".into(),
            serde_json::to_value(&self.timings_ms).unwrap_or(Value::Null),
        );
        out.insert(
            "per_frame".into(),
            serde_json::to_value(&self.per_frame).unwrap_or(Value::Null),
        );
        Value::Object(out)
    }

    /// A table per frame, then the summary and the stage timings.
    pub fn table(&self) -> String {
        let cell = |v: Option<f64>| v.map_or_else(|| "-".to_owned(), |v| format!("{v:.3}"));
        let mut out = String::from(
            "frame  tracking   pose mm  pose °  obj px  depth mm  albedo  light °  comp real  comp virt  Δ rel L2  Δ oracle  Δ noise\n",
        );
        for (i, f) in self.per_frame.iter().enumerate() {
            out.push_str(&format!(
                "{i:>5}  {:<9} {:>8} {:>7} {:>7} {:>9} {:>7} {:>8} {:>10.4} {:>10.4} {:>9.4} {:>9.4} {:>8.4}\n",
                f.tracking,
                cell(f.pose_error_mm),
                cell(f.pose_error_deg),
                cell(f.object_reprojection_px),
                cell(f.depth_rmse_mm),
                cell(f.albedo_rel_error),
                cell(f.light_direction_error_deg),
                f.composite_rel_l2_real,
                f.composite_rel_l2_virtual,
                f.delta_rel_l2,
                f.delta_rel_l2_oracle,
                f.delta_truth_noise,
            ));
        }
        out.push_str(&format!(
            "\n{}: engine {}, {} frame sets, {} tracked, {} scored\n{:<30} {:>10} {:>10} {:>7}\n",
            self.recording,
            self.engine,
            self.frames,
            self.tracked_frames,
            self.scored_frames,
            "measure",
            "median",
            "p95",
            "frames"
        ));
        for name in MEASURES {
            if let Some(s) = self.measures.get(name) {
                out.push_str(&format!(
                    "{name:<30} {:>10.4} {:>10.4} {:>7}\n",
                    s.median, s.p95, s.frames
                ));
            }
        }
        out.push_str("\nstage                          mean ms\n");
        for (name, ms) in &self.timings_ms {
            out.push_str(&format!("{name:<30} {ms:>8.2}\n"));
        }
        out
    }
}

fn finite(v: f64) -> Value {
    if v.is_finite() { v.into() } else { Value::Null }
}

/// The light of `estimate` against that of `truth`, both as seen at `point` (the probe: a
/// distant-light estimate is right where it was measured, and off elsewhere by the real lights'
/// parallax, which is the light model's error, not the estimate's). The main light's direction
/// is that of the irradiance vector `Σ E_i ω_i` (a median cut splits one bright light into
/// several of equal energy, so "the strongest single light" would compare the pieces); the
/// ratio is of the total irradiance `Σ E_i` (luminance). Direction error (°) and ratio.
pub fn main_light_error(estimate: &[Light], truth: &[Light], point: Vec3) -> Option<(f64, f64)> {
    let moments = |lights: &[Light]| {
        lights
            .iter()
            .filter_map(|light| light.incident(point))
            .filter(|incident| incident.irradiance.is_finite())
            .fold((Vec3::ZERO, 0.0f32), |(vector, total), incident| {
                let e = incident.irradiance.dot(LUMINANCE);
                (vector + incident.direction_to_light * e, total + e)
            })
    };
    let (estimate, truth) = (moments(estimate), moments(truth));
    let (Some(e), Some(t)) = (estimate.0.try_normalize(), truth.0.try_normalize()) else {
        return None;
    };
    (truth.1 > 0.0).then(|| {
        (
            f64::from(e.dot(t).clamp(-1.0, 1.0).acos().to_degrees()),
            f64::from(estimate.1 / truth.1),
        )
    })
}

/// Rec. 709 luminance weights.
const LUMINANCE: Vec3 = Vec3::new(0.2126, 0.7152, 0.0722);

/// Translation (mm) and rotation (°) between two camera poses.
pub fn pose_difference(estimate: &Pose, truth: &Pose) -> (f64, f64) {
    let mm = f64::from((estimate.translation - truth.translation).length()) * 1e3;
    let relative = estimate.rotation.as_dquat() * truth.rotation.as_dquat().inverse();
    let deg = relight_backends::markers::pose::rotation_angle(relative).to_degrees();
    (mm, deg)
}

/// Mean distance, pixels, between `points_in_world` projected with the estimated and the true
/// camera pose; `None` when a point does not project in either.
pub fn reprojection_px(
    camera: &relight_core::camera::Pinhole,
    points_in_world: &[Vec3],
    estimate: &Pose,
    truth: &Pose,
) -> Option<f64> {
    if points_in_world.is_empty() {
        return None;
    }
    let project = |world_from_camera: &Pose, p: Vec3| {
        let in_camera = world_from_camera.inverse().transform_point(p);
        camera.project(optical_from_gl(in_camera.as_dvec3()))
    };
    let mut sum = 0.0;
    for p in points_in_world {
        sum += (project(estimate, *p)? - project(truth, *p)?).length();
    }
    Some(sum / points_in_world.len() as f64)
}

/// RMS difference, metres, over pixels where both depth images have a surface. `estimate` is
/// the truth's size or every n-th of its pixels ([`Image::subsampled`]: the depth stage
/// reconstructs only the `[scene] depth_stride` grid the mesh takes).
pub fn depth_rmse_m(estimate: &Image, truth: &Image) -> Option<f64> {
    if estimate.width() == 0 || truth.width() == 0 {
        return None;
    }
    let step = truth.width().div_ceil(estimate.width());
    if (truth.width().div_ceil(step), truth.height().div_ceil(step))
        != (estimate.width(), estimate.height())
    {
        return None;
    }
    let (mut sum, mut n) = (0.0f64, 0usize);
    for y in 0..estimate.height() {
        for x in 0..estimate.width() {
            if let (Some(e), Some(t)) = (estimate.depth_m(x, y), truth.depth_m(x * step, y * step))
                && e.is_finite()
                && t.is_finite()
                && e > 0.0
                && t > 0.0
            {
                sum += f64::from(e - t).powi(2);
                n += 1;
            }
        }
    }
    (n > 0).then(|| (sum / n as f64).sqrt())
}

/// ‖a_est − a_true‖ / ‖a_true‖ over the real surfaces' vertices that land on a pixel with a
/// true surface: each vertex's albedo as the engines get it (measured, else its material's),
/// against the true albedo where the estimated pose projects it. The truth's albedo is Rgba16F,
/// read as Δ is.
fn albedo_error(
    scene: &Scene,
    camera: &relight_core::camera::Pinhole,
    world_from_camera: &Pose,
    albedo: &Image,
    depth: Option<&Image>,
) -> Option<f64> {
    let truth = delta_pixels(albedo);
    let camera_from_world = world_from_camera.inverse();
    let (mut err, mut norm) = (0.0f64, 0.0f64);
    for mesh in scene.meshes.iter().filter(|m| !m.is_virtual) {
        let material = scene
            .materials
            .get(mesh.material)
            .map_or(Vec3::ZERO, |m| m.albedo);
        for (v, p) in mesh.positions_in_world.iter().enumerate() {
            let in_camera = camera_from_world.transform_point(*p);
            let Some(pixel) = camera.project(optical_from_gl(in_camera.as_dvec3())) else {
                continue;
            };
            let (x, y) = (pixel.x.round(), pixel.y.round());
            if x < 0.0
                || y < 0.0
                || x >= f64::from(albedo.width())
                || y >= f64::from(albedo.height())
            {
                continue;
            }
            let (x, y) = (x as u32, y as u32);
            if depth.is_some_and(|d| d.depth_m(x, y).is_none_or(|z| z.is_nan() || z <= 0.0)) {
                continue;
            }
            let Some(true_albedo) = truth.get((y * albedo.width() + x) as usize) else {
                continue;
            };
            let estimate = mesh.measured_albedo(v as u32).unwrap_or(material);
            err += f64::from((estimate - *true_albedo).length_squared());
            norm += f64::from(true_albedo.length_squared());
        }
    }
    (norm > 0.0).then(|| (err / norm).sqrt())
}

/// ‖a‖₂ over the pixels `mask` selects.
fn l2(a: &[Vec3], mask: &[bool]) -> f64 {
    a.iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .map(|(x, _)| f64::from(x.length_squared()))
        .sum::<f64>()
        .sqrt()
}

/// ‖a − b‖₂ / ‖b‖₂ over the pixels `mask` selects; NaN on mismatched sizes, an empty mask or a
/// zero `b` there (the bench's `offline::delta_error` floors the norm instead; a frame whose
/// true Δ is zero must drop out of the summaries here, not dominate them).
pub fn relative_l2(a: &[Vec3], b: &[Vec3], mask: &[bool]) -> f64 {
    offline::masked_relative_l2(a, b, mask).unwrap_or(f64::NAN)
}

/// Δ as linear RGB; zeros when the engine drew none (untracked, or a failed frame).
fn delta_or_zero(delta: &Image, pixels: usize) -> Vec<Vec3> {
    let pixels_of = delta_pixels(delta);
    if pixels_of.len() == pixels {
        pixels_of
    } else {
        vec![Vec3::ZERO; pixels]
    }
}

/// `relightd score`'s settings from the live defaults.
pub fn default_config() -> Config {
    Config {
        path: Path::new("(relightd score)").to_owned(),
        ..Config::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_are_nearest_rank() {
        let v = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0];
        assert_eq!(quantile(&v, 0.5), 5.0);
        assert_eq!(quantile(&v, 0.95), 10.0);
        assert!(quantile(&[], 0.5).is_nan());
    }

    #[test]
    fn a_shifted_pose_reprojects_by_its_parallax() {
        let camera = relight_core::camera::Pinhole {
            width: 160,
            height: 120,
            fx: 100.0,
            fy: 100.0,
            cx: 79.5,
            cy: 59.5,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        };
        let truth = Pose::IDENTITY;
        let moved = Pose::from_translation(Vec3::new(0.01, 0.0, 0.0));
        let points = [Vec3::new(0.0, 0.0, -2.0), Vec3::new(0.1, 0.1, -2.0)];
        // 1 cm sideways at 2 m: 100 px · 0.01 / 2 = 0.5 px.
        let px = reprojection_px(&camera, &points, &moved, &truth).unwrap();
        assert!((px - 0.5).abs() < 1e-4, "{px}");
        let (mm, deg) = pose_difference(&moved, &truth);
        assert!((mm - 10.0).abs() < 1e-3 && deg.abs() < 1e-6);
    }
}
