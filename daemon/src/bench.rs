//! `relightd bench`: every engine × setting × scene → median frame time and the error of its Δ
//! against the reference path tracer (relative L2 over real pixels, and max |Δ − Δ_ref|),
//! printed as a table and written as CSV, JSON and a speed-vs-error plot (SVG).
//!
//! Each scene is rendered once by the reference (full light transport, pixel centres, so the
//! engines' rasterised silhouettes line up), whose L^μ is also the camera image; each engine is built once per setting, run on the
//! same offline [`SceneFrame`] the daemon would give it, warmed up,
//! then timed over `frames` renders: wall clock of `Engine::render`, including the readback of Δ
//! and the composite (what the pipeline waits for), and the GPU time of its passes from
//! timestamp queries where the adapter has them.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use glam::Vec3;
use plotters::prelude::*;
use relight_core::Image;
use relight_core::scene::Scene;
use relight_engines::offline::{
    Sampling, TermErrors, Transport, background, composite_pixels, delta_error, delta_pixels,
    object_error, reference_noise, reference_renderer, region_errors, scene_frame, term_errors,
};
use relight_engines::reference::{ReferenceImages, ReferenceRenderer};
use relight_engines::reference_cache::ReferenceCache;
use relight_engines::roofline::{PassWork, Rates};
use relight_engines::{EngineRegistry, RelitFrame, SceneFrame};
use serde::Serialize;
use serde_json::{Map, Value, json};

/// One engine setting to measure.
#[derive(Debug, Clone)]
pub struct BenchCase {
    pub engine: String,
    pub params: Map<String, Value>,
}

impl BenchCase {
    /// `engine` with `params` (a JSON object; anything else is no parameters).
    pub fn new(engine: &str, params: Value) -> Self {
        Self {
            engine: engine.into(),
            params: params.as_object().cloned().unwrap_or_default(),
        }
    }

    /// A setting as [`BenchCase::label`] writes it (bench.csv's `setting` column): the engine,
    /// then `name=value` pairs (values as JSON where they parse), checked against the engine's
    /// parameters, so a row of one run can be measured again on its own.
    pub fn parse(setting: &str, registry: &EngineRegistry) -> Result<Self> {
        let mut words = setting.split_whitespace();
        let engine = words
            .next()
            .context("an empty setting: expected an engine, then name=value pairs")?;
        let spec = registry.spec(engine)?;
        let mut params = Map::new();
        for pair in words {
            let (name, value) = relight_engines::params::parse_assignment(pair)
                .with_context(|| format!("`{pair}` in `{setting}`: expected name=value"))?;
            params.insert(name.to_owned(), value);
        }
        spec.schema
            .validate(&spec.schema.defaults(), &params)
            .with_context(|| format!("`{setting}`"))?;
        Ok(Self {
            engine: engine.to_owned(),
            params,
        })
    }

    pub fn label(&self) -> String {
        let params: Vec<String> = self
            .params
            .iter()
            .map(|(k, v)| format!("{k}={}", v.to_string().trim_matches('"')))
            .collect();
        if params.is_empty() {
            self.engine.clone()
        } else {
            format!("{} {}", self.engine, params.join(" "))
        }
    }
}

/// The default cases: each engine at its defaults, and with `sweep` the paper's parameter
/// sweeps (DLPV: volume 16³/32³/64³ × steps 8/16/32/64, RSM 256²/512²/1024²; DVCT: volume
/// 32³/64³/128³/256³ × step 0.25/0.5/1; DIR: 64/128/256/512/1024 VPLs, ISM 32²/64²/128²; IBL:
/// maps 32²/64²/128², 4/16/32 shadow lights; the
/// differential baseline's shadow-map sizes). A setting an adapter cannot hold is logged and
/// left out of the results.
pub fn default_cases(sweep: bool) -> Vec<BenchCase> {
    let mut cases = vec![
        BenchCase::new("differential", json!({})),
        BenchCase::new("dlpv", json!({})),
        BenchCase::new("dlpv", json!({ "shadows": "antiradiance" })),
        BenchCase::new("dvct", json!({})),
        BenchCase::new("dvct", json!({ "shadows": "cones" })),
        BenchCase::new("dir", json!({})),
        BenchCase::new("ibl", json!({})),
        BenchCase::new("pt", json!({})),
    ];
    if sweep {
        for rsm in [256, 1024] {
            cases.push(BenchCase::new("differential", json!({ "rsm_size": rsm })));
        }
        for volume in [16, 32, 64] {
            for steps in [8, 16, 32, 64] {
                cases.push(BenchCase::new(
                    "dlpv",
                    json!({ "volume_size": volume, "steps": steps }),
                ));
            }
        }
        for rsm in [128, 512] {
            cases.push(BenchCase::new("dlpv", json!({ "rsm_size": rsm })));
        }
        for vpls in [64, 128, 512, 1024] {
            cases.push(BenchCase::new("dir", json!({ "vpl_count": vpls })));
        }
        for ism in [64, 128] {
            cases.push(BenchCase::new("dir", json!({ "ism_size": ism })));
        }
        for size in [32, 128] {
            cases.push(BenchCase::new("ibl", json!({ "map_size": size })));
        }
        for lights in [4, 32] {
            cases.push(BenchCase::new("ibl", json!({ "env_lights": lights })));
        }
        for volume in [32, 64, 128, 256] {
            for step in [0.25, 0.5, 1.0] {
                cases.push(BenchCase::new(
                    "dvct",
                    json!({ "volume_size": volume, "step": step }),
                ));
            }
        }
    }
    cases
}

#[derive(Debug, Clone)]
pub struct BenchSettings {
    pub scenes: Vec<PathBuf>,
    pub width: u32,
    pub height: u32,
    /// Samples per pixel the reference starts with.
    pub reference_spp: u32,
    /// The most it is refined to (see [`run`]); at most `reference_spp` turns refining off.
    pub max_reference_spp: u32,
    /// Where references are kept between runs ([`ReferenceCache`]); `None`: always render.
    pub reference_cache: Option<PathBuf>,
    pub frames: u32,
    /// Still frames every GPU engine accumulates (its `accumulate` parameter) in place of the
    /// case's own or the engine's default; 1 scores no converged picture.
    pub accumulate: Option<u32>,
    /// Also render each engine that has an `indirect` parameter with its direct light alone,
    /// and a direct-light reference, and score which term each error comes from
    /// ([`TermErrors`]).
    pub terms: bool,
    /// Time each GPU pass by waiting for it rather than by timestamp queries
    /// ([`GpuContext::set_wait_per_pass`](relight_engines::gpu::GpuContext::set_wait_per_pass)):
    /// `gpu_passes` is then each pass's own time on any adapter, lavapipe's included, and the
    /// frame times are slower by what the passes no longer overlap.
    pub wait_per_pass: bool,
    pub cases: Vec<BenchCase>,
}

#[derive(Debug, Clone, Serialize)]
pub struct BenchRow {
    pub scene: String,
    pub engine: String,
    pub setting: String,
    /// Median frame time with every input changed since the previous frame (the real geometry
    /// moves by 10 µm on alternate frames), so nothing drawn before can be kept: a live frame.
    pub median_ms: f64,
    pub min_ms: f64,
    /// Median frame time when nothing changed since the previous frame: a still scene, where
    /// an engine keeps what it may (the shadow maps, `Deferred::prepare`).
    pub static_ms: f64,
    /// Median frame time once the still frames' mean is complete (after `accumulate` of them)
    /// and nothing changed: the frame shows the mean and draws nothing (`Deferred::prepare`),
    /// what a still camera costs after its edges converged. `None` without accumulation.
    pub held_ms: Option<f64>,
    /// Median GPU time of the frame's passes by timestamp queries, or by waiting for each with
    /// [`BenchSettings::wait_per_pass`] (`None` where the adapter has no timestamp queries).
    pub gpu_ms: Option<f64>,
    /// GPU time per pass of the last timed frame (its inputs changed, as every timed frame's).
    pub gpu_passes: Vec<(String, f64)>,
    /// What each pass of that frame had to do ([`RelitFrame::work`]), for the roofline.
    #[serde(skip)]
    pub pass_work: Vec<PassWork>,
    /// ‖Δ − Δ_ref‖₂ / ‖Δ_ref‖₂ over real pixels.
    pub relative_l2: f64,
    /// max |Δ − Δ_ref| over real pixels and channels.
    pub max_abs: f64,
    /// ‖C − L^ρ_ref‖₂ / ‖L^ρ_ref‖₂ of the composite over the virtual object's pixels
    /// ([`object_error`]); `None` (JSON `null`) when the object covers no pixel.
    pub object_relative_l2: Option<f64>,
    /// `relative_l2` over the object's shadow alone, and over its bleeding alone: the real
    /// pixels where the reference's Δ is significantly negative or positive
    /// ([`region_errors`]); `None` where the reference has no such pixel.
    pub shadow_relative_l2: Option<f64>,
    pub bleeding_relative_l2: Option<f64>,
    /// The reference's own noise in the metric of `relative_l2` ([`reference_noise`]): the
    /// row's error reads about √(e² + noise²) for a true error e.
    pub reference_noise: f64,
    /// Samples per pixel of the reference the row was scored against.
    pub reference_spp: u32,
    /// Still frames the engine accumulated over sub-pixel offsets for the converged scores
    /// (its `accumulate` parameter; 1: none).
    pub accumulated_frames: u32,
    /// The pixel-centre frame above against the reference over each pixel's area, which a
    /// camera sees: the part of the error the centre samples add is `area_relative_l2` less
    /// `converged_relative_l2`.
    pub area_relative_l2: Option<f64>,
    /// ‖Δ − Δ_ref‖₂ / ‖Δ_ref‖₂ over real pixels once `accumulated_frames` still frames are
    /// averaged, against the pixel-area reference; `None` without accumulation.
    pub converged_relative_l2: Option<f64>,
    /// The object's pixels of that converged composite against the pixel-area L^ρ.
    pub converged_object_relative_l2: Option<f64>,
    /// The pixel-area reference's noise and samples per pixel.
    pub area_reference_noise: Option<f64>,
    pub area_reference_spp: Option<u32>,
    /// With `--terms`: the error of `relative_l2` left when the reference's indirect term
    /// replaces the engine's (its direct light's error) and when the reference's direct term
    /// replaces the engine's (its indirect light's), over real pixels ([`TermErrors`]); `None`
    /// for an engine without an `indirect` parameter.
    pub direct_term_relative_l2: Option<f64>,
    pub indirect_term_relative_l2: Option<f64>,
    /// The same of `object_relative_l2`, over the object's pixels.
    pub object_direct_term_relative_l2: Option<f64>,
    pub object_indirect_term_relative_l2: Option<f64>,
    /// The direct-light reference's noise in the metric of `relative_l2`, and its samples.
    pub direct_reference_noise: Option<f64>,
    pub direct_reference_spp: Option<u32>,
    /// The split of `converged_relative_l2` alike, against the pixel-area references: what
    /// is left of each term once the edges have converged.
    pub converged_direct_term_relative_l2: Option<f64>,
    pub converged_indirect_term_relative_l2: Option<f64>,
}

/// What a row is scored from, kept until the scene's references are final.
struct Rendered {
    /// The first frame after a change: pixel centres.
    centre: Picture,
    /// After the engine's accumulation completed, still.
    converged: Option<Picture>,
    /// As `centre`, shaded without the engine's indirect term (`indirect=off`, with
    /// `--terms`).
    direct: Option<Picture>,
    /// As `converged`, without the indirect term.
    direct_converged: Option<Picture>,
}

struct Picture {
    delta: Vec<Vec3>,
    composite: Image,
}

impl Picture {
    fn of(out: &RelitFrame) -> Self {
        Self {
            delta: delta_pixels(&out.delta),
            composite: out.composite.clone(),
        }
    }

    /// Which term Δ's error over real pixels comes from, given `alone`, this picture's
    /// direct term alone, and the full and direct-light references ([`term_errors`]).
    fn delta_terms(
        &self,
        alone: &Picture,
        full: &ReferenceImages,
        direct: &ReferenceImages,
    ) -> Option<TermErrors> {
        let real: Vec<bool> = full.virtual_mask.iter().map(|v| !v).collect();
        term_errors(
            &self.delta,
            &alone.delta,
            &full.delta,
            &direct.delta,
            &real,
            false,
        )
    }

    /// Δ's error over real pixels (relative L2, max) and the object's.
    fn errors(&self, reference: &ReferenceImages) -> ((f64, f64), Option<f64>) {
        (
            delta_error(&self.delta, &reference.delta, &reference.virtual_mask),
            object_error(&self.composite, &reference.l_rho, &reference.virtual_mask),
        )
    }
}

impl BenchRow {
    /// (Re)score the centre frame against `reference` (pixel centres).
    fn score(&mut self, rendered: &Rendered, reference: &ReferenceImages) {
        ((self.relative_l2, self.max_abs), self.object_relative_l2) =
            rendered.centre.errors(reference);
        let regions = region_errors(&rendered.centre.delta, reference);
        self.shadow_relative_l2 = regions.shadow_relative_l2;
        self.bleeding_relative_l2 = regions.bleeding_relative_l2;
        self.reference_noise = reference_noise(reference);
        self.reference_spp = reference.spp;
    }

    /// (Re)score both pictures against `reference` (pixel areas).
    fn score_area(&mut self, rendered: &Rendered, reference: &ReferenceImages) {
        self.area_relative_l2 = Some(rendered.centre.errors(reference).0.0);
        if let Some(converged) = &rendered.converged {
            let ((delta, _), object) = converged.errors(reference);
            self.converged_relative_l2 = Some(delta);
            self.converged_object_relative_l2 = object;
        }
        self.area_reference_noise = Some(reference_noise(reference));
        self.area_reference_spp = Some(reference.spp);
    }

    /// (Re)score which term the centre frame's errors come from, against the full reference
    /// `full` and the direct-light one `direct` (pixel centres both).
    fn score_terms(
        &mut self,
        rendered: &Rendered,
        full: &ReferenceImages,
        direct: &ReferenceImages,
    ) {
        let Some(alone) = &rendered.direct else {
            return;
        };
        let split =
            |terms: Option<TermErrors>| (terms.map(|t| t.direct), terms.map(|t| t.indirect));
        (self.direct_term_relative_l2, self.indirect_term_relative_l2) =
            split(rendered.centre.delta_terms(alone, full, direct));
        (
            self.object_direct_term_relative_l2,
            self.object_indirect_term_relative_l2,
        ) = split(term_errors(
            &composite_pixels(&rendered.centre.composite),
            &composite_pixels(&alone.composite),
            &full.l_rho,
            &direct.l_rho,
            &full.virtual_mask,
            true,
        ));
        self.direct_reference_noise = Some(reference_noise(direct));
        self.direct_reference_spp = Some(direct.spp);
    }

    /// (Re)score which term the converged picture's Δ error comes from, against the
    /// pixel-area references.
    fn score_converged_terms(
        &mut self,
        rendered: &Rendered,
        full: &ReferenceImages,
        direct: &ReferenceImages,
    ) {
        let (Some(converged), Some(alone)) = (&rendered.converged, &rendered.direct_converged)
        else {
            return;
        };
        let terms = converged.delta_terms(alone, full, direct);
        self.converged_direct_term_relative_l2 = terms.map(|t| t.direct);
        self.converged_indirect_term_relative_l2 = terms.map(|t| t.indirect);
    }
}

/// One of a scene's references: read from the cache or rendered, then refined while its noise
/// is above a third of the best row's error, and cached once final.
pub(crate) struct Truth {
    sampling: Sampling,
    transport: Transport,
    cache: Option<(ReferenceCache, u64)>,
    /// The renderer it was rendered or refined with this run (a cached one starts afresh).
    renderer: Option<ReferenceRenderer>,
    pub(crate) images: ReferenceImages,
}

impl Truth {
    pub(crate) fn new(
        settings: &BenchSettings,
        dir: &Path,
        scene: &Scene,
        sampling: Sampling,
        transport: Transport,
        progress: &mut impl FnMut(BenchProgress<'_>),
    ) -> Result<Self> {
        let (w, h) = (settings.width, settings.height);
        let spp = settings.reference_spp.max(2);
        let cache = settings.reference_cache.as_ref().and_then(|dir_of_cache| {
            let key = ReferenceCache::key(dir, w, h, sampling, transport).ok()?;
            Some((ReferenceCache::new(dir_of_cache), key))
        });
        let cached = cache
            .as_ref()
            .and_then(|(cache, key)| cache.load(*key))
            .filter(|r| r.spp >= spp && (r.width, r.height) == (w, h));
        let (images, renderer) = match cached {
            Some(images) => {
                progress(BenchProgress::Reference {
                    scene: &scene.name,
                    sampling,
                    transport,
                    spp: images.spp,
                    cached: true,
                });
                (images, None)
            }
            None => {
                progress(BenchProgress::Reference {
                    scene: &scene.name,
                    sampling,
                    transport,
                    spp,
                    cached: false,
                });
                let mut renderer = reference_renderer(scene, w, h, sampling, transport)?;
                renderer.add_samples(spp);
                (renderer.images(), Some(renderer))
            }
        };
        Ok(Self {
            sampling,
            transport,
            cache,
            renderer,
            images,
        })
    }

    /// Double the samples while the noise is above `best / 3` and below `max_spp` samples;
    /// whether any were added.
    pub(crate) fn refine(
        &mut self,
        scene: &Scene,
        best: f64,
        max_spp: u32,
        progress: &mut impl FnMut(BenchProgress<'_>),
    ) -> Result<bool> {
        let mut refined = false;
        while reference_noise(&self.images) > best / 3.0 && self.images.spp < max_spp {
            let target = self.images.spp.saturating_mul(2).min(max_spp);
            progress(BenchProgress::Reference {
                scene: &scene.name,
                sampling: self.sampling,
                transport: self.transport,
                spp: target,
                cached: false,
            });
            let renderer = match self.renderer.take() {
                Some(renderer) => renderer,
                None => reference_renderer(
                    scene,
                    self.images.width,
                    self.images.height,
                    self.sampling,
                    self.transport,
                )?,
            };
            let renderer = self.renderer.insert(renderer);
            renderer.add_samples(target.saturating_sub(renderer.spp()));
            self.images = renderer.images();
            refined = true;
        }
        Ok(refined)
    }

    /// Keep it in the cache if it was rendered this run.
    pub(crate) fn store(&self, scene: &str) {
        if self.renderer.is_some()
            && let Some((cache, key)) = &self.cache
            && let Err(error) = cache.store(*key, &self.images)
        {
            tracing::warn!(%error, "{scene}: reference not cached");
        }
    }
}

/// What [`run`] is doing, for a progress display.
#[derive(Debug)]
pub enum BenchProgress<'a> {
    /// Rendering (or refining) `scene`'s reference to `spp` samples per pixel, or, `cached`,
    /// reading one of `spp` from the reference cache.
    Reference {
        scene: &'a str,
        sampling: Sampling,
        transport: Transport,
        spp: u32,
        cached: bool,
    },
    /// Measuring case `done + 1` of `total` (over all scenes).
    Case {
        scene: &'a str,
        setting: String,
        done: usize,
        total: usize,
    },
    /// A row, final (scored against its scene's final reference).
    Row(&'a BenchRow),
}

/// Measure every case on every scene.
///
/// Per scene, the reference starts at `reference_spp` samples; after every case has rendered,
/// samples are added (doubling) until the reference's noise is under a third of the best row's
/// error, or `max_reference_spp` is reached, and every row is scored against that final
/// reference. `progress` sees each scene's rows once they are final.
pub fn run(
    settings: &BenchSettings,
    mut progress: impl FnMut(BenchProgress<'_>),
) -> Result<Vec<BenchRow>> {
    let registry = EngineRegistry::new();
    if settings.wait_per_pass {
        registry
            .gpu()
            .context("timing passes by waiting needs a GPU adapter")?
            .set_wait_per_pass(true);
    }
    let total = settings.scenes.len() * settings.cases.len();
    let mut rows = Vec::new();
    for (scene_index, dir) in settings.scenes.iter().enumerate() {
        let scene = Arc::new(Scene::load(dir)?);
        let mut centre = Truth::new(
            settings,
            dir,
            &scene,
            Sampling::Centre,
            Transport::Full,
            &mut progress,
        )?;
        let frame = scene_frame(scene.clone(), background(&centre.images));
        let mut scene_rows: Vec<(BenchRow, Rendered)> = Vec::new();
        for (case_index, case) in settings.cases.iter().enumerate() {
            progress(BenchProgress::Case {
                scene: &scene.name,
                setting: case.label(),
                done: scene_index * settings.cases.len() + case_index,
                total,
            });
            // A setting this adapter cannot hold (a volume beyond its storage limits) costs that
            // row only: the error names the limit and the setting.
            match measure(
                &registry,
                case,
                settings,
                &scene.name,
                &frame,
                &centre.images,
            ) {
                Ok(measured) => scene_rows.push(measured),
                Err(e) => tracing::warn!("{}: skipped: {e:#}", scene.name),
            }
        }
        let max_spp = settings.max_reference_spp;
        settle(
            &mut centre,
            &scene,
            &mut scene_rows,
            max_spp,
            |row, rendered, truth| row.score(rendered, truth),
            |row| Some(row.relative_l2),
            &mut progress,
        )?;
        // The direct-light reference the term split swaps in (its noise enters both terms).
        if scene_rows.iter().any(|(_, r)| r.direct.is_some()) {
            let mut direct = Truth::new(
                settings,
                dir,
                &scene,
                Sampling::Centre,
                Transport::Direct,
                &mut progress,
            )?;
            settle(
                &mut direct,
                &scene,
                &mut scene_rows,
                max_spp,
                |row, rendered, truth| row.score_terms(rendered, &centre.images, truth),
                |row| least(row.direct_term_relative_l2, row.indirect_term_relative_l2),
                &mut progress,
            )?;
        }
        // The pixel-area truth the accumulated frames converge to, where any row has them.
        if scene_rows.iter().any(|(_, r)| r.converged.is_some()) {
            let mut area = Truth::new(
                settings,
                dir,
                &scene,
                Sampling::Area,
                Transport::Full,
                &mut progress,
            )?;
            settle(
                &mut area,
                &scene,
                &mut scene_rows,
                max_spp,
                |row, rendered, truth| row.score_area(rendered, truth),
                |row| row.converged_relative_l2,
                &mut progress,
            )?;
            // And the pixel-area direct-light reference the converged term split swaps in.
            if scene_rows.iter().any(|(_, r)| r.direct_converged.is_some()) {
                let mut direct = Truth::new(
                    settings,
                    dir,
                    &scene,
                    Sampling::Area,
                    Transport::Direct,
                    &mut progress,
                )?;
                settle(
                    &mut direct,
                    &scene,
                    &mut scene_rows,
                    max_spp,
                    |row, rendered, truth| row.score_converged_terms(rendered, &area.images, truth),
                    |row| {
                        least(
                            row.converged_direct_term_relative_l2,
                            row.converged_indirect_term_relative_l2,
                        )
                    },
                    &mut progress,
                )?;
            }
        }
        for (row, _) in scene_rows {
            progress(BenchProgress::Row(&row));
            rows.push(row);
        }
    }
    Ok(rows)
}

/// Score every row against `truth`, refine it while its noise is above a third of the least
/// of the rows' `error`s (within `max_spp`), score them again if it was, and keep it in the
/// cache.
fn settle(
    truth: &mut Truth,
    scene: &Scene,
    rows: &mut [(BenchRow, Rendered)],
    max_spp: u32,
    score: impl Fn(&mut BenchRow, &Rendered, &ReferenceImages),
    error: impl Fn(&BenchRow) -> Option<f64>,
    progress: &mut impl FnMut(BenchProgress<'_>),
) -> Result<()> {
    let score_all = |rows: &mut [(BenchRow, Rendered)], truth: &Truth| {
        for (row, rendered) in rows {
            score(row, rendered, &truth.images);
        }
    };
    score_all(rows, truth);
    let best = rows
        .iter()
        .filter_map(|(row, _)| error(row))
        .filter(|e| e.is_finite())
        .fold(f64::INFINITY, f64::min);
    if truth.refine(scene, best, max_spp, progress)? {
        score_all(rows, truth);
    }
    truth.store(&scene.name);
    Ok(())
}

/// The lesser of a row's two term errors, where it has both.
fn least(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    a.zip(b).map(|(a, b)| a.min(b))
}

/// `scene` with its first real vertex moved by 10 µm: the same picture to the shadow maps'
/// resolution, but new geometry to every cache.
fn nudged(scene: &Scene) -> Scene {
    let mut scene = scene.clone();
    if let Some(p) = scene
        .meshes
        .iter_mut()
        .find(|m| !m.is_virtual)
        .and_then(|m| m.positions_in_world.first_mut())
    {
        p.x += 1e-5;
    }
    scene
}

/// Warm up, time `frames` renders of one case with every input changing, then `frames` with
/// nothing changing. Scored: the first frame after a change (pixel centres, as live) and, for
/// an engine that accumulates, the still frame its accumulation completes on.
fn measure(
    registry: &EngineRegistry,
    case: &BenchCase,
    settings: &BenchSettings,
    scene: &str,
    frame: &SceneFrame,
    reference: &ReferenceImages,
) -> Result<(BenchRow, Rendered)> {
    let frames = settings.frames.max(1);
    let spec = registry.spec(&case.engine)?;
    let mut params = case.params.clone();
    if let Some(accumulate) = settings.accumulate
        && spec.schema.has("accumulate")
    {
        params.insert("accumulate".into(), accumulate.into());
    }
    let built = registry
        .build(&case.engine, &params)
        .with_context(|| case.label())?;
    let accumulated_frames = built
        .params
        .get("accumulate")
        .and_then(Value::as_u64)
        .map_or(1, |n| n.max(1) as u32);
    let mut engine = built.engine;
    let mut out = RelitFrame::default();
    let nudged = SceneFrame {
        scene: frame.scene.as_deref().map(|s| Arc::new(nudged(s))),
        ..frame.clone()
    };
    let mut render = |frame: &SceneFrame, out: &mut RelitFrame| -> Result<f64> {
        let started = Instant::now();
        engine.render(frame, out).with_context(|| case.label())?;
        Ok(started.elapsed().as_secs_f64() * 1e3)
    };
    for _ in 0..2 {
        render(frame, &mut out)?;
    }
    let mut times = Vec::new();
    let mut gpu_times = Vec::new();
    for i in 0..frames {
        times.push(render(if i % 2 == 0 { &nudged } else { frame }, &mut out)?);
        let gpu: Vec<f64> = out
            .timings
            .iter()
            .filter(|t| t.pass.starts_with("gpu."))
            .map(|t| t.ms)
            .collect();
        if !gpu.is_empty() {
            gpu_times.push(gpu.iter().sum::<f64>());
        }
    }
    times.sort_by(f64::total_cmp);
    gpu_times.sort_by(f64::total_cmp);
    let gpu_passes = out
        .timings
        .iter()
        .filter_map(|t| Some((t.pass.strip_prefix("gpu.")?.to_owned(), t.ms)))
        .collect();
    let pass_work = out.work.clone();
    // The unchanged frame once more after a changed one (the nudged frame, or the warm-up's
    // last): the picture a live frame shows. Then timed as it repeats.
    render(&nudged, &mut out)?;
    render(frame, &mut out)?;
    let centre = Picture::of(&out);
    let static_ms = median(
        &mut (0..frames)
            .map(|_| render(frame, &mut out))
            .collect::<Result<Vec<f64>>>()?,
    );
    let (converged, held_ms) = if accumulated_frames > 1 {
        for _ in frames + 1..accumulated_frames {
            render(frame, &mut out)?;
        }
        let converged = Picture::of(&out);
        let held_ms = median(
            &mut (0..frames)
                .map(|_| render(frame, &mut out))
                .collect::<Result<Vec<f64>>>()?,
        );
        (Some(converged), Some(held_ms))
    } else {
        (None, None)
    };
    // The centre frame once more, shaded without the engine's indirect term, and the still
    // frames it converges over.
    let (direct, direct_converged) = if settings.terms && spec.schema.has("indirect") {
        let mut direct_params = built.params.clone();
        direct_params.insert("indirect".into(), "off".into());
        engine.set_params(&direct_params);
        for frame in [&nudged, frame] {
            engine
                .render(frame, &mut out)
                .with_context(|| case.label())?;
        }
        let centre = Picture::of(&out);
        let converged = if accumulated_frames > 1 {
            for _ in 1..accumulated_frames {
                engine
                    .render(frame, &mut out)
                    .with_context(|| case.label())?;
            }
            Some(Picture::of(&out))
        } else {
            None
        };
        (Some(centre), converged)
    } else {
        (None, None)
    };
    let rendered = Rendered {
        centre,
        converged,
        direct,
        direct_converged,
    };
    let mut row = BenchRow {
        scene: scene.to_owned(),
        engine: case.engine.clone(),
        setting: case.label(),
        median_ms: times[times.len() / 2],
        min_ms: times[0],
        static_ms,
        held_ms,
        gpu_ms: gpu_times.get(gpu_times.len() / 2).copied(),
        gpu_passes,
        pass_work,
        relative_l2: f64::NAN,
        max_abs: f64::NAN,
        object_relative_l2: None,
        shadow_relative_l2: None,
        bleeding_relative_l2: None,
        reference_noise: f64::NAN,
        reference_spp: 0,
        accumulated_frames,
        area_relative_l2: None,
        converged_relative_l2: None,
        converged_object_relative_l2: None,
        area_reference_noise: None,
        area_reference_spp: None,
        direct_term_relative_l2: None,
        indirect_term_relative_l2: None,
        object_direct_term_relative_l2: None,
        object_indirect_term_relative_l2: None,
        direct_reference_noise: None,
        direct_reference_spp: None,
        converged_direct_term_relative_l2: None,
        converged_indirect_term_relative_l2: None,
    };
    row.score(&rendered, reference);
    Ok((row, rendered))
}

/// Median of `times` (sorted in place); NaN when there are none.
pub(crate) fn median(times: &mut [f64]) -> f64 {
    times.sort_by(f64::total_cmp);
    times.get(times.len() / 2).copied().unwrap_or(f64::NAN)
}

pub fn table(rows: &[BenchRow]) -> String {
    let mut s = format!(
        "{:<14} {:<48} {:>10} {:>10} {:>10} {:>10} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>7} {:>9} {:>9} {:>9} {:>10}\n",
        "scene",
        "engine / setting",
        "median ms",
        "static ms",
        "held ms",
        "GPU ms",
        "rel L2",
        "shadow",
        "bleeding",
        "max abs",
        "object L2",
        "ref noise",
        "ref spp",
        "area L2",
        "conv L2",
        "conv obj",
        "area noise"
    );
    let or_dash = |v: Option<f64>| v.map_or("-".to_owned(), |e| format!("{e:.4}"));
    for r in rows {
        let gpu = r.gpu_ms.map_or("-".to_owned(), |ms| format!("{ms:.2}"));
        s.push_str(&format!(
            "{:<14} {:<48} {:>10.2} {:>10.2} {:>10} {:>10} {:>9.4} {:>9} {:>9} {:>9.4} {:>9} {:>9.4} {:>7} {:>9} {:>9} {:>9} {:>10}\n",
            r.scene,
            r.setting,
            r.median_ms,
            r.static_ms,
            r.held_ms.map_or("-".to_owned(), |ms| format!("{ms:.2}")),
            gpu,
            r.relative_l2,
            or_dash(r.shadow_relative_l2),
            or_dash(r.bleeding_relative_l2),
            r.max_abs,
            or_dash(r.object_relative_l2),
            r.reference_noise,
            r.reference_spp,
            or_dash(r.area_relative_l2),
            or_dash(r.converged_relative_l2),
            or_dash(r.converged_object_relative_l2),
            or_dash(r.area_reference_noise)
        ));
    }
    s
}

/// Which term each row's errors come from (`--terms`, [`TermErrors`]): beside the error of Δ
/// on real pixels and of the object's pixels, the error left with the reference's indirect
/// term swapped in (the engine's direct term's) and with its direct term swapped in (the
/// indirect term's).
pub fn terms_table(rows: &[BenchRow]) -> String {
    let mut s = format!(
        "{:<14} {:<48} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>10} {:>7} {:>9} {:>9} {:>9}\n",
        "scene",
        "engine / setting",
        "rel L2",
        "direct",
        "indirect",
        "object L2",
        "obj dir",
        "obj ind",
        "ref noise",
        "dir noise",
        "dir spp",
        "conv L2",
        "conv dir",
        "conv ind"
    );
    let or_dash = |v: Option<f64>| v.map_or("-".to_owned(), |e| format!("{e:.4}"));
    for r in rows {
        s.push_str(&format!(
            "{:<14} {:<48} {:>9.4} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9.4} {:>10} {:>7} {:>9} {:>9} {:>9}\n",
            r.scene,
            r.setting,
            r.relative_l2,
            or_dash(r.direct_term_relative_l2),
            or_dash(r.indirect_term_relative_l2),
            or_dash(r.object_relative_l2),
            or_dash(r.object_direct_term_relative_l2),
            or_dash(r.object_indirect_term_relative_l2),
            r.reference_noise,
            or_dash(r.direct_reference_noise),
            r.direct_reference_spp
                .map_or("-".to_owned(), |n| n.to_string()),
            or_dash(r.converged_relative_l2),
            or_dash(r.converged_direct_term_relative_l2),
            or_dash(r.converged_indirect_term_relative_l2)
        ));
    }
    s
}

/// One pass of one bench row against the adapter's roofline (`bench --roofline`).
#[derive(Debug, Clone, Serialize)]
pub struct RooflineRow {
    pub scene: String,
    pub engine: String,
    pub setting: String,
    pub pass: String,
    /// The pass's GPU time (timestamp queries) in the last timed frame.
    pub ms: f64,
    /// What its algorithm must move and compute ([`relight_engines::roofline::Work`]);
    /// `None` for a pass without a work model.
    pub bytes: Option<f64>,
    pub ops: Option<f64>,
    /// That work at the adapter's rates, and which rate bounds it (`memory` or `alu`).
    pub roofline_ms: Option<f64>,
    pub bound: Option<&'static str>,
    /// `roofline_ms / ms`: 1 is the adapter's limit.
    pub roofline_fraction: Option<f64>,
}

/// Every timed pass of every row, with its work where the engine stated one.
pub fn roofline_rows(rows: &[BenchRow], rates: &Rates) -> Vec<RooflineRow> {
    let mut out = Vec::new();
    for row in rows {
        for (pass, ms) in &row.gpu_passes {
            let work = row
                .pass_work
                .iter()
                .filter(|w| w.pass == pass)
                .map(|w| w.work)
                .reduce(|a, b| a + b);
            let roofline = work.map(|w| rates.roofline_ms(w));
            out.push(RooflineRow {
                scene: row.scene.clone(),
                engine: row.engine.clone(),
                setting: row.setting.clone(),
                pass: pass.clone(),
                ms: *ms,
                bytes: work.map(|w| w.bytes),
                ops: work.map(|w| w.ops),
                roofline_ms: roofline.map(|(ms, _)| ms),
                bound: roofline.map(|(_, bound)| bound.name()),
                roofline_fraction: work.map(|w| rates.fraction(w, *ms)),
            });
        }
    }
    out
}

pub fn roofline_table(rates: &Rates, rows: &[RooflineRow]) -> String {
    let mut s = format!(
        "roofline: {:.2} GB/s (copy), {:.2} Gop/s (fma)\n{:<14} {:<40} {:<10} {:>10} {:>10} {:>10} {:>12} {:>7} {:>9}\n",
        rates.bytes_per_s / 1e9,
        rates.ops_per_s / 1e9,
        "scene",
        "engine / setting",
        "pass",
        "ms",
        "MB",
        "Mop",
        "roofline ms",
        "bound",
        "fraction"
    );
    let or_dash = |v: Option<f64>, scale: f64, digits: usize| {
        v.map_or("-".to_owned(), |v| format!("{:.*}", digits, v * scale))
    };
    for r in rows {
        s.push_str(&format!(
            "{:<14} {:<40} {:<10} {:>10.2} {:>10} {:>10} {:>12} {:>7} {:>9}\n",
            r.scene,
            r.setting,
            r.pass,
            r.ms,
            or_dash(r.bytes, 1e-6, 1),
            or_dash(r.ops, 1e-6, 1),
            or_dash(r.roofline_ms, 1.0, 3),
            r.bound.unwrap_or("-"),
            or_dash(r.roofline_fraction, 1.0, 4),
        ));
    }
    s
}

/// `roofline.csv` and `roofline.json` (with the rates) in `dir`.
pub fn write_roofline(
    rates: &Rates,
    rows: &[RooflineRow],
    dir: &Path,
    adapter: &str,
) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let or_empty = |v: Option<f64>| v.map_or(String::new(), |e| e.to_string());
    let mut csv = String::from(
        "scene,engine,setting,pass,ms,bytes,ops,roofline_ms,bound,roofline_fraction\n",
    );
    for r in rows {
        csv.push_str(&format!(
            "{},{},\"{}\",{},{},{},{},{},{},{}\n",
            r.scene,
            r.engine,
            r.setting,
            r.pass,
            r.ms,
            or_empty(r.bytes),
            or_empty(r.ops),
            or_empty(r.roofline_ms),
            r.bound.unwrap_or(""),
            or_empty(r.roofline_fraction)
        ));
    }
    std::fs::write(dir.join("roofline.csv"), csv)?;
    std::fs::write(
        dir.join("roofline.json"),
        serde_json::to_string_pretty(&json!({
            "adapter": adapter,
            "bytes_per_s": rates.bytes_per_s,
            "ops_per_s": rates.ops_per_s,
            "rows": rows,
        }))?,
    )?;
    Ok(())
}

/// `bench.csv`, `bench.json` and `bench.svg` (frame time vs error, one colour per engine) in
/// `dir`.
pub fn write_outputs(rows: &[BenchRow], dir: &Path, adapter: &str) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut csv = String::from(
        "scene,engine,setting,median_ms,min_ms,static_ms,held_ms,gpu_ms,relative_l2,shadow_relative_l2,bleeding_relative_l2,max_abs,object_relative_l2,reference_noise,reference_spp,accumulated_frames,area_relative_l2,converged_relative_l2,converged_object_relative_l2,area_reference_noise,area_reference_spp,direct_term_relative_l2,indirect_term_relative_l2,object_direct_term_relative_l2,object_indirect_term_relative_l2,direct_reference_noise,direct_reference_spp,converged_direct_term_relative_l2,converged_indirect_term_relative_l2\n",
    );
    let or_empty = |v: Option<f64>| v.map_or(String::new(), |e| e.to_string());
    for r in rows {
        csv.push_str(&format!(
            "{},{},\"{}\",{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            r.scene,
            r.engine,
            r.setting,
            r.median_ms,
            r.min_ms,
            r.static_ms,
            or_empty(r.held_ms),
            or_empty(r.gpu_ms),
            r.relative_l2,
            or_empty(r.shadow_relative_l2),
            or_empty(r.bleeding_relative_l2),
            r.max_abs,
            or_empty(r.object_relative_l2),
            r.reference_noise,
            r.reference_spp,
            r.accumulated_frames,
            or_empty(r.area_relative_l2),
            or_empty(r.converged_relative_l2),
            or_empty(r.converged_object_relative_l2),
            or_empty(r.area_reference_noise),
            r.area_reference_spp
                .map_or(String::new(), |n| n.to_string()),
            or_empty(r.direct_term_relative_l2),
            or_empty(r.indirect_term_relative_l2),
            or_empty(r.object_direct_term_relative_l2),
            or_empty(r.object_indirect_term_relative_l2),
            or_empty(r.direct_reference_noise),
            r.direct_reference_spp
                .map_or(String::new(), |n| n.to_string()),
            or_empty(r.converged_direct_term_relative_l2),
            or_empty(r.converged_indirect_term_relative_l2)
        ));
    }
    std::fs::write(dir.join("bench.csv"), csv)?;
    std::fs::write(
        dir.join("bench.json"),
        serde_json::to_string_pretty(&json!({ "adapter": adapter, "rows": rows }))?,
    )?;
    plot(rows, &dir.join("bench.svg"), adapter)
}

/// The sensor's frame period: a live engine must fit under it.
const FRAME_BUDGET_MS: f64 = 1000.0 / 30.0;

/// Frame time against Δ error, one panel per scene on shared axes (log time, so 0.1 ms and 5 s
/// both read), one colour per engine, each point labelled with its setting, and the 33 ms
/// budget of a 30 Hz sensor as a vertical line.
fn plot(rows: &[BenchRow], path: &Path, adapter: &str) -> Result<()> {
    let plot_error = |e: DrawingAreaErrorKind<_>| anyhow::anyhow!("{e}");
    let finite: Vec<&BenchRow> = rows
        .iter()
        .filter(|r| r.median_ms.is_finite() && r.relative_l2.is_finite() && r.median_ms > 0.0)
        .collect();
    let min_ms = finite
        .iter()
        .map(|r| r.median_ms)
        .fold(FRAME_BUDGET_MS, f64::min)
        / 1.5;
    let max_ms = finite
        .iter()
        .map(|r| r.median_ms)
        .fold(FRAME_BUDGET_MS, f64::max)
        * 1.5;
    let max_err = finite.iter().map(|r| r.relative_l2).fold(0.1, f64::max) * 1.15;
    let mut scenes: Vec<&str> = finite.iter().map(|r| r.scene.as_str()).collect();
    scenes.dedup();
    let mut engines: Vec<&str> = finite.iter().map(|r| r.engine.as_str()).collect();
    engines.sort_unstable();
    engines.dedup();
    let columns = scenes.len().clamp(1, 3);
    let panel_rows = scenes.len().div_ceil(columns).max(1);
    let size = (480 * columns as u32, 400 * panel_rows as u32 + 40);
    let root = SVGBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(plot_error)?;
    let root = root
        .titled(
            &format!("relight engines: frame time vs Δ error ({adapter})"),
            ("sans-serif", 20),
        )
        .map_err(plot_error)?;
    let panels = root.split_evenly((panel_rows, columns));
    for (scene, panel) in scenes.iter().zip(&panels) {
        let mut chart = ChartBuilder::on(panel)
            .caption(*scene, ("sans-serif", 16))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(48)
            .build_cartesian_2d((min_ms..max_ms).log_scale(), 0.0f64..max_err)
            .map_err(plot_error)?;
        chart
            .configure_mesh()
            .x_desc("median frame time (ms, log)")
            .y_desc("relative L2 of Δ (real pixels)")
            .draw()
            .map_err(plot_error)?;
        chart
            .draw_series(LineSeries::new(
                [(FRAME_BUDGET_MS, 0.0), (FRAME_BUDGET_MS, max_err)],
                RED.stroke_width(1),
            ))
            .map_err(plot_error)?
            .label("33 ms (30 Hz)")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 16, y)], RED));
        for (i, engine) in engines.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            let points: Vec<(f64, f64, String)> = finite
                .iter()
                .filter(|r| r.scene == *scene && r.engine == *engine)
                .map(|r| {
                    let setting = r.setting.strip_prefix(engine).unwrap_or(&r.setting).trim();
                    let label = if setting.is_empty() {
                        "defaults"
                    } else {
                        setting
                    };
                    (r.median_ms, r.relative_l2, label.to_owned())
                })
                .collect();
            chart
                .draw_series(points.iter().map(|(ms, error, label)| {
                    EmptyElement::at((*ms, *error))
                        + Circle::new((0, 0), 4, colour.filled())
                        + Text::new(label.clone(), (6, -4), ("sans-serif", 9))
                }))
                .map_err(plot_error)?
                .label(*engine)
                .legend(move |(x, y)| Circle::new((x + 8, y), 4, colour.filled()));
        }
        chart
            .configure_series_labels()
            .border_style(BLACK)
            .background_style(WHITE.mix(0.8))
            .draw()
            .map_err(plot_error)?;
    }
    root.present().map_err(plot_error)?;
    Ok(())
}

/// One row of the reflection-map timing (`relightd bench --ibl-maps`).
#[derive(Debug, Clone, Serialize)]
pub struct MapTiming {
    /// Output maps are `size × size` texels (octahedral), the input about as many.
    pub size: u32,
    pub input_texels: usize,
    pub levels: usize,
    /// Median wall clock of one convolution of all maps, submit to completion.
    pub median_ms: f64,
}

/// Kan et al.'s timing table: the diffuse map and `levels` specular maps convolved in one pass
/// at each output size S² from an input of about S² texels (an equirectangular sky with a sun,
/// every texel non-black, so none is skipped), median of `repeats` runs after one warm-up.
pub fn ibl_map_timings(sizes: &[u32], levels: u32, repeats: u32) -> Result<Vec<MapTiming>> {
    use relight_engines::gpu::GpuContext;
    use relight_engines::ibl::maps::{ReflectionMaps, input_texels, log_spaced_shininess};

    let ctx = GpuContext::new().context("the map convolution needs a GPU adapter")?;
    let shininess = log_spaced_shininess(levels.max(1));
    let mut rows = Vec::new();
    for &size in sizes {
        let width = (f64::from(size) * std::f64::consts::SQRT_2).round() as u32;
        let texels = input_texels(&sky(width.max(2), (width / 2).max(1)), None);
        let mut maps = ReflectionMaps::new(&ctx);
        let mut times = Vec::new();
        for run in 0..=repeats.max(1) {
            let started = Instant::now();
            maps.convolve(&ctx, &texels, size, &shininess, &mut None)
                .with_context(|| format!("convolving {size}² maps"))?;
            ctx.wait().context("waiting for the GPU")?;
            if run > 0 {
                times.push(started.elapsed().as_secs_f64() * 1e3);
            }
        }
        times.sort_by(f64::total_cmp);
        rows.push(MapTiming {
            size,
            input_texels: texels.len(),
            levels: shininess.len(),
            median_ms: times[times.len() / 2],
        });
    }
    Ok(rows)
}

/// A sky for timing: a vertical gradient, a dim ground and a small bright sun.
fn sky(width: u32, height: u32) -> relight_core::scene::EnvironmentMap {
    use glam::Vec3;
    let radiance = (0..width * height)
        .map(|i| {
            let (x, y) = (i % width, i / width);
            let v = (y as f32 + 0.5) / height as f32;
            let sun = x * 8 / width == 3 && y * 8 / height == 2;
            if sun {
                Vec3::splat(1e4)
            } else if v < 0.5 {
                Vec3::new(0.4, 0.6, 1.0) * (1.0 - v)
            } else {
                Vec3::splat(0.1)
            }
        })
        .collect();
    relight_core::scene::EnvironmentMap {
        width,
        height,
        radiance,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_setting_reads_back_as_its_label_writes_it() {
        let registry = EngineRegistry::new();
        for case in default_cases(true) {
            let parsed = BenchCase::parse(&case.label(), &registry).unwrap();
            assert_eq!((parsed.engine, parsed.params), (case.engine, case.params));
        }
        let case = BenchCase::parse("dir  second_bounce=0 vpl_count=64", &registry).unwrap();
        assert_eq!(case.label(), "dir second_bounce=0 vpl_count=64");
    }

    #[test]
    fn a_bad_setting_says_what_is_wrong() {
        let registry = EngineRegistry::new();
        let error = |setting| format!("{:#}", BenchCase::parse(setting, &registry).unwrap_err());
        assert!(error("").contains("empty setting"));
        assert!(error("dri").contains("unknown engine `dri`"));
        assert!(
            error("dir vpl_count").contains("`vpl_count` in `dir vpl_count`: expected name=value")
        );
        let out_of_range = error("dir vpl_count=0");
        assert!(
            out_of_range.contains("`dir vpl_count=0`") && out_of_range.contains("vpl_count"),
            "{out_of_range}"
        );
        assert!(error("dir no_such=1").contains("no_such"));
    }
}
