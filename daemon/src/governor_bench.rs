//! `relightd bench --governor`: does `auto` meet a frame budget with the least error? For each
//! scene and budget, `auto`'s error at its frame time against every fixed engine (the governor's
//! candidates at their parameters, `pt` at the budget) that fits the budget, on the adapter at
//! hand; and `pt`'s error against time beside the CPU reference's at equal time.
//!
//! **Scenes (a still camera): the picture [`GovernorSettings::seconds`] after the scene
//! appears.** Each engine is built (`auto` with all its candidates, as a daemon builds an engine
//! before it swaps it in) and renders a first frame; then each renders the scene's frame for
//! that long on its own clock, no faster than a 30 Hz sensor delivers frames: everything it
//! accumulates (the rasterisers' sub-pixel edges, `pt`'s samples) and, for `auto`, its probes
//! and switches happen on that clock. The engines take their frames in turn, so a slow spell
//! of the machine falls on all of them alike. Its time is the median frame over its clock
//! (`clock_median_ms`: the frame the run is in at its middle instant); its error that of
//! the last frame's Δ (relative L2 over real pixels) against the reference over each pixel's
//! area (what a camera sees, and what still frames converge to).
//! `auto`'s horizon is set to the same time. A fixed engine fits when that frame is within
//! the budget; `auto` **matches** the best one that fits when its error is at most
//! [`MATCH_TOLERANCE`] above it (the references' noise is reported beside).
//!
//! **The bundled recording (a moving camera).** `relightd score` per engine (every frame's
//! inputs change): the median Δ error against the recording's truth, the mean render time.
//!
//! **pt's curve.** `pt` at one sample per pixel per frame, accumulating; the CPU reference
//! (another seed than the truth's) doubling its samples; each point the error after that much
//! wall-clock time.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use glam::Vec3;
use plotters::prelude::*;
use relight_core::scene::Scene;
use relight_engines::auto::Auto;
use relight_engines::auto::governor::candidates;
use relight_engines::offline::{
    Sampling, Transport, background, delta_error, delta_pixels, scene_frame,
};
use relight_engines::reference::{ReferenceImages, ReferenceRenderer, ReferenceSettings};
use relight_engines::{Engine, EngineRegistry, RelitFrame, SceneFrame};
use serde::Serialize;
use serde_json::{Map, Value, json};

use crate::bench::{BenchProgress, BenchSettings, Truth};
use crate::score::{ScoreSettings, default_config};

/// `auto` matches the best fixed engine within 5 % of its error.
pub const MATCH_TOLERANCE: f64 = 0.05;
/// Frames come no faster than a 30 Hz sensor's.
const SENSOR_PERIOD: Duration = Duration::from_nanos(1_000_000_000 / 30);

#[derive(Debug, Clone)]
pub struct GovernorSettings {
    /// Scenes, size and references (its `cases` are not used).
    pub bench: BenchSettings,
    pub budgets_ms: Vec<f64>,
    /// How long each engine renders a still scene, seconds (`auto`'s horizon too).
    pub seconds: f64,
    /// A simulated recording and its scene, run through the live path per engine.
    pub recording: Option<(PathBuf, PathBuf)>,
    /// Samples per pixel of the recording's truth renders.
    pub recording_reference_spp: u32,
    /// Wall-clock seconds of `pt`'s and the reference's error curves (0: none).
    pub curve_seconds: f64,
}

/// One engine's run on one scene.
#[derive(Debug, Clone, Serialize)]
pub struct EngineRun {
    pub scene: String,
    /// The setting (`auto budget_ms=33` for auto).
    pub engine: String,
    pub budget_ms: Option<f64>,
    pub median_ms: f64,
    pub relative_l2: f64,
    /// Frames rendered in the run.
    pub frames: usize,
    /// Path samples per pixel in the last frame's picture (`pt`, or `auto` running it).
    pub path_samples: f64,
    /// For `auto`: what it chose and its switches.
    pub chosen: Option<String>,
    pub switches: Option<u64>,
    /// `auto`'s status after its run: the features, every candidate's prediction and cost.
    pub status: Option<Value>,
}

/// The comparison at one budget on one scene (the JSON rows).
#[derive(Debug, Clone, Serialize)]
pub struct GovernorRow {
    pub scene: String,
    pub budget_ms: f64,
    pub auto_engine: String,
    pub auto_relative_l2: f64,
    pub auto_ms: f64,
    /// The fixed engine with the least error among those whose median frame (over the run's
    /// clock) fits the budget; `None` when none fits.
    pub best_fixed_engine: Option<String>,
    pub best_fixed_relative_l2: Option<f64>,
    pub best_fixed_ms: Option<f64>,
    pub fixed_that_fit: usize,
    /// `beats`, `matches` (within [`MATCH_TOLERANCE`]), `worse`, or `none fits`.
    pub verdict: &'static str,
    /// The truth's own noise in the metric (the scenes' area reference; NaN for the
    /// recording, whose truth frames are rendered at `recording_reference_spp`).
    pub reference_noise: f64,
}

/// A point of an error-against-time curve.
#[derive(Debug, Clone, Serialize)]
pub struct CurvePoint {
    pub scene: String,
    /// `pt` or `reference` (the CPU path tracer).
    pub renderer: &'static str,
    pub seconds: f64,
    pub spp: u32,
    pub relative_l2: f64,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct GovernorReport {
    pub rows: Vec<GovernorRow>,
    pub runs: Vec<EngineRun>,
    pub curve: Vec<CurvePoint>,
}

/// What the run is doing, for a progress display.
#[derive(Debug)]
pub enum GovernorProgress<'a> {
    Reference(BenchProgress<'a>),
    Run { scene: &'a str, engine: String },
}

/// One engine's run on a scene: frames no faster than the sensor's, on the engine's own clock.
struct Timeline {
    label: String,
    /// The budget the setting depends on (`pt`'s and `auto`'s).
    budget_ms: Option<f64>,
    engine: Box<dyn Engine>,
    /// Its clock: each frame advances it by the frame's time or the sensor's period, whichever
    /// is longer (a frame that takes less waits for the next).
    clock: Duration,
    times: Vec<f64>,
    out: RelitFrame,
}

/// Render `frame` with every engine for `seconds` of each engine's own clock (as
/// [`Timeline::clock`] runs), the engines taking their frames in turn, so that a slow spell of
/// a shared machine falls on all of them alike (run one after another, two runs of one engine
/// were seen 8 % apart in error). Each engine renders a first frame before its clock starts:
/// it allocates and uploads, and on lavapipe takes from 0.6 s (`dir` alone) to 3.7 s (`dir`
/// beside the other engines), which would leave a slow engine a frame or two of the run.
fn run_in_turn(lines: &mut [Timeline], frame: &SceneFrame, seconds: f64) -> Result<()> {
    for line in lines.iter_mut() {
        line.engine.render(frame, &mut line.out)?;
    }
    let end = Duration::from_secs_f64(seconds);
    // The engine furthest behind renders next.
    while let Some(line) = lines
        .iter_mut()
        .filter(|l| l.clock < end)
        .min_by_key(|l| l.clock)
    {
        let started = Instant::now();
        line.engine.render(frame, &mut line.out)?;
        let took = started.elapsed();
        line.times.push(took.as_secs_f64() * 1e3);
        line.clock += took.max(SENSOR_PERIOD);
    }
    Ok(())
}

/// The frame time (ms) at the middle of a run's clock: the frames sorted by time, each
/// weighted by the clock it takes (at least a sensor period), the first at which half the
/// clock is reached. A plain median counts frames: an engine that spends 2 s converging at
/// 65–300 ms a frame and then holds its picture at 2 ms has more held frames than converging
/// ones in 4 s, and its median (2 ms) said it fitted a 10 ms budget it misses for half the run.
fn clock_median_ms(times_ms: &[f64]) -> f64 {
    let period_ms = SENSOR_PERIOD.as_secs_f64() * 1e3;
    let mut sorted: Vec<f64> = times_ms.iter().copied().filter(|t| t.is_finite()).collect();
    sorted.sort_by(f64::total_cmp);
    let clock: f64 = sorted.iter().map(|t| t.max(period_ms)).sum();
    let mut passed = 0.0;
    for t in &sorted {
        passed += t.max(period_ms);
        if passed >= 0.5 * clock {
            return *t;
        }
    }
    f64::NAN
}

/// An engine with parameters, as the bench runs it.
struct Setting {
    label: String,
    engine: &'static str,
    params: Map<String, Value>,
    /// The budget the setting depends on.
    budget_ms: Option<f64>,
}

/// The fixed settings compared at `budget`: the governor's candidates, `pt` at the budget.
fn fixed_settings(budget_ms: f64) -> Vec<Setting> {
    candidates()
        .into_iter()
        .map(|c| {
            let mut setting = Setting {
                label: c.label.clone(),
                engine: c.engine,
                params: c.params.clone(),
                budget_ms: None,
            };
            if c.is_path_traced() {
                setting.params.insert("budget_ms".into(), json!(budget_ms));
                setting.label = format!("pt budget_ms={budget_ms}");
                setting.budget_ms = Some(budget_ms);
            }
            setting
        })
        .collect()
}

/// Every fixed setting once (only `pt`'s depends on the budget), and `auto` per budget.
fn settings_to_run(budgets_ms: &[f64]) -> Vec<Setting> {
    let mut to_run: Vec<Setting> = Vec::new();
    for &budget in budgets_ms {
        for setting in fixed_settings(budget) {
            if !to_run.iter().any(|s| s.label == setting.label) {
                to_run.push(setting);
            }
        }
        let params = json!({ "budget_ms": budget });
        to_run.push(Setting {
            label: format!("auto budget_ms={budget}"),
            engine: Auto::NAME,
            params: params.as_object().cloned().unwrap_or_default(),
            budget_ms: Some(budget),
        });
    }
    to_run
}

/// The comparison of `auto` with the fixed runs at one budget.
fn compare(
    scene: &str,
    budget_ms: f64,
    auto: &EngineRun,
    fixed: &[&EngineRun],
    reference_noise: f64,
) -> GovernorRow {
    let fitting: Vec<&&EngineRun> = fixed
        .iter()
        .filter(|r| r.median_ms <= budget_ms && r.relative_l2.is_finite())
        .collect();
    let best = fitting
        .iter()
        .min_by(|a, b| a.relative_l2.total_cmp(&b.relative_l2));
    let verdict = match best {
        None => "none fits",
        Some(b) if auto.relative_l2 < b.relative_l2 => "beats",
        Some(b) if auto.relative_l2 <= b.relative_l2 * (1.0 + MATCH_TOLERANCE) => "matches",
        Some(_) => "worse",
    };
    GovernorRow {
        scene: scene.to_owned(),
        budget_ms,
        auto_engine: auto.chosen.clone().unwrap_or_default(),
        auto_relative_l2: auto.relative_l2,
        auto_ms: auto.median_ms,
        best_fixed_engine: best.map(|b| b.engine.clone()),
        best_fixed_relative_l2: best.map(|b| b.relative_l2),
        best_fixed_ms: best.map(|b| b.median_ms),
        fixed_that_fit: fitting.len(),
        verdict,
        reference_noise,
    }
}

/// Every scene and budget, the recording, and the curves.
pub fn run(
    settings: &GovernorSettings,
    mut progress: impl FnMut(GovernorProgress<'_>),
) -> Result<GovernorReport> {
    let registry = EngineRegistry::new();
    let mut report = GovernorReport::default();
    for dir in &settings.bench.scenes {
        let scene = Arc::new(Scene::load(dir)?);
        let name = scene.name.clone();
        let mut truth = Truth::new(
            &settings.bench,
            dir,
            &scene,
            Sampling::Area,
            Transport::Full,
            &mut |p| progress(GovernorProgress::Reference(p)),
        )?;
        let frame = scene_frame(scene.clone(), background(&truth.images));
        // Built before the runs start, as a running daemon builds an engine before it swaps it
        // in; `auto`'s candidates too.
        let build = |engine: &str, params: &Map<String, Value>| -> Result<Box<dyn Engine>> {
            if engine != Auto::NAME {
                return Ok(registry.build(engine, params)?.engine);
            }
            let mut auto = Auto::new(&registry).context("auto")?;
            let schema = Auto::schema();
            let mut params = schema.validate(&schema.defaults(), params)?;
            params.insert("horizon_ms".into(), json!(settings.seconds * 1e3));
            auto.set_params(&params);
            auto.wait_for_builds();
            Ok(Box::new(auto))
        };
        let mut lines = Vec::new();
        for setting in settings_to_run(&settings.budgets_ms) {
            progress(GovernorProgress::Run {
                scene: &name,
                engine: setting.label.clone(),
            });
            match build(setting.engine, &setting.params) {
                Ok(engine) => lines.push(Timeline {
                    label: setting.label,
                    budget_ms: setting.budget_ms,
                    engine,
                    clock: Duration::ZERO,
                    times: Vec::new(),
                    out: RelitFrame::default(),
                }),
                Err(error) if setting.engine == Auto::NAME => return Err(error),
                Err(error) => tracing::warn!("{name}: {} skipped: {error:#}", setting.label),
            }
        }
        run_in_turn(&mut lines, &frame, settings.seconds)?;
        // Each run keeps its last Δ until the truth is final.
        let mut runs: Vec<(EngineRun, Vec<Vec3>)> = lines
            .into_iter()
            .map(|line| {
                let status = line.engine.status();
                (
                    EngineRun {
                        scene: name.clone(),
                        engine: line.label,
                        budget_ms: line.budget_ms,
                        median_ms: clock_median_ms(&line.times),
                        relative_l2: f64::NAN,
                        frames: line.times.len(),
                        path_samples: line.out.path_samples,
                        chosen: status
                            .as_ref()
                            .and_then(|s| s["chosen"].as_str().map(str::to_owned)),
                        switches: status.as_ref().and_then(|s| s["switches"].as_u64()),
                        status,
                    },
                    delta_pixels(&line.out.delta),
                )
            })
            .collect();
        let score = |runs: &mut Vec<(EngineRun, Vec<Vec3>)>, truth: &ReferenceImages| {
            for (run, delta) in runs {
                run.relative_l2 = delta_error(delta, &truth.delta, &truth.virtual_mask).0;
            }
        };
        score(&mut runs, &truth.images);
        let best = runs
            .iter()
            .map(|(r, _)| r.relative_l2)
            .filter(|e| e.is_finite())
            .fold(f64::INFINITY, f64::min);
        if truth.refine(&scene, best, settings.bench.max_reference_spp, &mut |p| {
            progress(GovernorProgress::Reference(p))
        })? {
            score(&mut runs, &truth.images);
        }
        truth.store(&name);
        let noise = relight_engines::offline::reference_noise(&truth.images);
        for &budget in &settings.budgets_ms {
            let fixed: Vec<&EngineRun> = runs
                .iter()
                .map(|(r, _)| r)
                .filter(|r| !r.engine.starts_with("auto"))
                .filter(|r| r.budget_ms.is_none_or(|b| b == budget))
                .collect();
            if let Some((auto, _)) = runs
                .iter()
                .find(|(r, _)| r.engine.starts_with("auto") && r.budget_ms == Some(budget))
            {
                report
                    .rows
                    .push(compare(&name, budget, auto, &fixed, noise));
            }
        }
        if settings.curve_seconds > 0.0 {
            report
                .curve
                .extend(curves(&registry, &scene, &frame, &truth.images, settings)?);
        }
        report.runs.extend(runs.into_iter().map(|(r, _)| r));
    }
    if let Some((recording, scene)) = &settings.recording {
        let (rows, runs) = recording_rows(recording, scene, settings, &mut progress)?;
        report.rows.extend(rows);
        report.runs.extend(runs);
    }
    Ok(report)
}

/// `pt` accumulating one sample per pixel per frame, and the CPU reference (seed 1; the
/// truth's is 0) doubling its samples, until `curve_seconds` each: the error after each step.
fn curves(
    registry: &EngineRegistry,
    scene: &Arc<Scene>,
    frame: &SceneFrame,
    truth: &ReferenceImages,
    settings: &GovernorSettings,
) -> Result<Vec<CurvePoint>> {
    let mut points = Vec::new();
    let error = |delta: &[Vec3]| delta_error(delta, &truth.delta, &truth.virtual_mask).0;
    let params = json!({ "spp": 1, "max_spp": 1 << 20 });
    let mut pt = registry
        .build("pt", params.as_object().unwrap_or(&Map::new()))?
        .engine;
    let mut out = RelitFrame::default();
    // The first frame compiles and uploads; time from the second on, as a running engine.
    pt.render(frame, &mut out)?;
    let started = Instant::now();
    let mut next_point = 1.0;
    while started.elapsed().as_secs_f64() < settings.curve_seconds {
        pt.render(frame, &mut out)?;
        if out.path_samples >= next_point {
            points.push(CurvePoint {
                scene: scene.name.clone(),
                renderer: "pt",
                seconds: started.elapsed().as_secs_f64(),
                spp: out.path_samples as u32,
                relative_l2: error(&delta_pixels(&out.delta)),
            });
            next_point *= 2.0;
        }
    }
    let (width, height) = (settings.bench.width, settings.bench.height);
    let mut cpu = ReferenceRenderer::new(
        scene,
        ReferenceSettings {
            seed: 1,
            size: Some((width, height)),
            ..ReferenceSettings::default()
        },
    )?;
    let started = Instant::now();
    let mut spp = 1;
    while started.elapsed().as_secs_f64() < settings.curve_seconds {
        cpu.add_samples(spp - cpu.spp());
        points.push(CurvePoint {
            scene: scene.name.clone(),
            renderer: "reference",
            seconds: started.elapsed().as_secs_f64(),
            spp: cpu.spp(),
            relative_l2: error(&cpu.images().delta),
        });
        spp *= 2;
    }
    Ok(points)
}

/// The recording through the live path per engine (`relightd score`): rows per budget.
fn recording_rows(
    recording: &Path,
    scene: &Path,
    settings: &GovernorSettings,
    progress: &mut impl FnMut(GovernorProgress<'_>),
) -> Result<(Vec<GovernorRow>, Vec<EngineRun>)> {
    let name = format!(
        "recording:{}",
        recording
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("?")
    );
    let score = |engine: &str, params: Map<String, Value>, label: String, budget: Option<f64>| {
        let report = crate::score::run(
            &ScoreSettings {
                recording: recording.to_owned(),
                scene: scene.to_owned(),
                engine: engine.to_owned(),
                params,
                reference_spp: settings.recording_reference_spp,
                reference_cache: settings.bench.reference_cache.clone(),
                out: None,
                config: default_config(),
                threads: false,
            },
            |_, _| {},
        )?;
        anyhow::Ok(EngineRun {
            scene: name.clone(),
            engine: label,
            budget_ms: budget,
            median_ms: report.timings_ms.get("render").copied().unwrap_or(f64::NAN),
            relative_l2: report
                .measures
                .get("delta_rel_l2")
                .map_or(f64::NAN, |s| s.median),
            frames: report.frames,
            // A moving camera's picture holds one frame's samples.
            path_samples: f64::NAN,
            chosen: report
                .engine_status
                .as_ref()
                .and_then(|s| s["chosen"].as_str().map(str::to_owned)),
            switches: report
                .engine_status
                .as_ref()
                .and_then(|s| s["switches"].as_u64()),
            status: report.engine_status,
        })
    };
    let mut runs = Vec::new();
    for setting in settings_to_run(&settings.budgets_ms) {
        progress(GovernorProgress::Run {
            scene: &name,
            engine: setting.label.clone(),
        });
        runs.push(score(
            setting.engine,
            setting.params,
            setting.label,
            setting.budget_ms,
        )?);
    }
    let rows = settings
        .budgets_ms
        .iter()
        .filter_map(|&budget| {
            let fixed: Vec<&EngineRun> = runs
                .iter()
                .filter(|r| !r.engine.starts_with("auto"))
                .filter(|r| r.budget_ms.is_none_or(|b| b == budget))
                .collect();
            let auto = runs
                .iter()
                .find(|r| r.engine.starts_with("auto") && r.budget_ms == Some(budget))?;
            Some(compare(&name, budget, auto, &fixed, f64::NAN))
        })
        .collect();
    Ok((rows, runs))
}

pub fn table(report: &GovernorReport) -> String {
    let mut s = format!(
        "{:<24} {:>9}  {:<30} {:>9} {:>9}  {:<30} {:>9} {:>9} {:>4}  {:<9} {:>9}\n",
        "scene",
        "budget",
        "auto chose",
        "auto L2",
        "auto ms",
        "best fixed that fits",
        "fixed L2",
        "fixed ms",
        "fit",
        "verdict",
        "ref noise"
    );
    let or_dash = |v: Option<f64>, digits: usize| v.map_or("-".into(), |v| format!("{v:.digits$}"));
    for r in &report.rows {
        s.push_str(&format!(
            "{:<24} {:>9.0}  {:<30} {:>9.4} {:>9.1}  {:<30} {:>9} {:>9} {:>4}  {:<9} {:>9.4}\n",
            r.scene,
            r.budget_ms,
            r.auto_engine,
            r.auto_relative_l2,
            r.auto_ms,
            r.best_fixed_engine.as_deref().unwrap_or("-"),
            or_dash(r.best_fixed_relative_l2, 4),
            or_dash(r.best_fixed_ms, 1),
            r.fixed_that_fit,
            r.verdict,
            r.reference_noise
        ));
    }
    for budget in report
        .rows
        .iter()
        .map(|r| r.budget_ms)
        .fold(Vec::<f64>::new(), |mut v, b| {
            if !v.contains(&b) {
                v.push(b);
            }
            v
        })
    {
        let scenes: Vec<&GovernorRow> = report
            .rows
            .iter()
            .filter(|r| r.budget_ms == budget && !r.scene.starts_with("recording:"))
            .collect();
        let good = scenes
            .iter()
            .filter(|r| matches!(r.verdict, "beats" | "matches" | "none fits"))
            .count();
        s.push_str(&format!(
            "{budget:>6.0} ms: auto matches or beats the best fixed engine that fits on {good} of {} scenes\n",
            scenes.len()
        ));
    }
    s
}

/// `governor.csv`, `governor.json` (rows, runs, curve), `governor.svg` (error against budget)
/// and `pt_curve.svg` (error against time) in `dir`.
pub fn write_outputs(report: &GovernorReport, dir: &Path, adapter: &str) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let or_empty = |v: Option<f64>| v.map_or(String::new(), |e| e.to_string());
    let mut csv = String::from(
        "scene,budget_ms,auto_engine,auto_relative_l2,auto_ms,best_fixed_engine,best_fixed_relative_l2,best_fixed_ms,fixed_that_fit,verdict,reference_noise\n",
    );
    for r in &report.rows {
        csv.push_str(&format!(
            "{},{},\"{}\",{},{},\"{}\",{},{},{},{},{}\n",
            r.scene,
            r.budget_ms,
            r.auto_engine,
            r.auto_relative_l2,
            r.auto_ms,
            r.best_fixed_engine.as_deref().unwrap_or(""),
            or_empty(r.best_fixed_relative_l2),
            or_empty(r.best_fixed_ms),
            r.fixed_that_fit,
            r.verdict,
            r.reference_noise
        ));
    }
    std::fs::write(dir.join("governor.csv"), csv)?;
    std::fs::write(
        dir.join("governor.json"),
        serde_json::to_string_pretty(&json!({
            "adapter": adapter,
            "rows": report.rows,
            "runs": report.runs,
            "curve": report.curve,
        }))?,
    )?;
    plot_budgets(report, &dir.join("governor.svg"), adapter)?;
    if !report.curve.is_empty() {
        plot_curve(report, &dir.join("pt_curve.svg"), adapter)?;
    }
    Ok(())
}

fn plot_error(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("{e}")
}

/// The scenes' panels on one drawing: one per name, three columns.
fn panels<'a>(
    path: &'a Path,
    count: usize,
    title: &str,
) -> Result<Vec<DrawingArea<SVGBackend<'a>, plotters::coord::Shift>>> {
    let columns = count.clamp(1, 3);
    let rows = count.div_ceil(columns).max(1);
    let root =
        SVGBackend::new(path, (420 * columns as u32, 340 * rows as u32 + 40)).into_drawing_area();
    root.fill(&WHITE).map_err(plot_error)?;
    let root = root.titled(title, ("sans-serif", 18)).map_err(plot_error)?;
    Ok(root.split_evenly((rows, columns)))
}

fn plot_budgets(report: &GovernorReport, path: &Path, adapter: &str) -> Result<()> {
    let mut scenes: Vec<&str> = report.rows.iter().map(|r| r.scene.as_str()).collect();
    scenes.dedup();
    let areas = panels(
        path,
        scenes.len(),
        &format!("auto against the best fixed engine that fits, by budget ({adapter})"),
    )?;
    for (scene, area) in scenes.iter().zip(&areas) {
        let rows: Vec<&GovernorRow> = report.rows.iter().filter(|r| r.scene == *scene).collect();
        let (lo, hi) = rows.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
            (lo.min(r.budget_ms), hi.max(r.budget_ms))
        });
        let top = rows
            .iter()
            .flat_map(|r| [Some(r.auto_relative_l2), r.best_fixed_relative_l2])
            .flatten()
            .filter(|e| e.is_finite())
            .fold(0.1, f64::max)
            * 1.15;
        let mut chart = ChartBuilder::on(area)
            .caption(*scene, ("sans-serif", 14))
            .margin(10)
            .x_label_area_size(32)
            .y_label_area_size(44)
            .build_cartesian_2d((lo / 1.5..hi * 1.5).log_scale(), 0.0..top)
            .map_err(plot_error)?;
        chart
            .configure_mesh()
            .x_desc("budget (ms, log)")
            .y_desc("relative L2 of Δ")
            .draw()
            .map_err(plot_error)?;
        let auto: Vec<(f64, f64)> = rows
            .iter()
            .map(|r| (r.budget_ms, r.auto_relative_l2))
            .collect();
        chart
            .draw_series(LineSeries::new(auto.clone(), BLUE.stroke_width(2)))
            .map_err(plot_error)?
            .label("auto")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 16, y)], BLUE));
        chart
            .draw_series(auto.iter().map(|p| Circle::new(*p, 3, BLUE.filled())))
            .map_err(plot_error)?;
        let fixed: Vec<(f64, f64)> = rows
            .iter()
            .filter_map(|r| Some((r.budget_ms, r.best_fixed_relative_l2?)))
            .collect();
        chart
            .draw_series(LineSeries::new(fixed.clone(), RED.stroke_width(1)))
            .map_err(plot_error)?
            .label("best fixed that fits")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 16, y)], RED));
        chart
            .draw_series(fixed.iter().map(|p| Cross::new(*p, 4, RED)))
            .map_err(plot_error)?;
        chart
            .configure_series_labels()
            .border_style(BLACK)
            .background_style(WHITE.mix(0.8))
            .draw()
            .map_err(plot_error)?;
    }
    Ok(())
}

fn plot_curve(report: &GovernorReport, path: &Path, adapter: &str) -> Result<()> {
    let mut scenes: Vec<&str> = report.curve.iter().map(|p| p.scene.as_str()).collect();
    scenes.dedup();
    let areas = panels(
        path,
        scenes.len(),
        &format!("error against time: pt ({adapter}) and the CPU reference"),
    )?;
    for (scene, area) in scenes.iter().zip(&areas) {
        let points: Vec<&CurvePoint> = report
            .curve
            .iter()
            .filter(|p| p.scene == *scene && p.relative_l2.is_finite() && p.relative_l2 > 0.0)
            .collect();
        let (t_lo, t_hi, e_lo, e_hi) = points.iter().fold(
            (f64::INFINITY, 0.0f64, f64::INFINITY, 0.0f64),
            |(a, b, c, d), p| {
                (
                    a.min(p.seconds),
                    b.max(p.seconds),
                    c.min(p.relative_l2),
                    d.max(p.relative_l2),
                )
            },
        );
        if points.is_empty() {
            continue;
        }
        let mut chart = ChartBuilder::on(area)
            .caption(*scene, ("sans-serif", 14))
            .margin(10)
            .x_label_area_size(32)
            .y_label_area_size(44)
            .build_cartesian_2d(
                (t_lo.max(1e-4) / 1.5..t_hi * 1.5).log_scale(),
                (e_lo / 1.5..e_hi * 1.5).log_scale(),
            )
            .map_err(plot_error)?;
        chart
            .configure_mesh()
            .x_desc("seconds (log)")
            .y_desc("relative L2 of Δ (log)")
            .draw()
            .map_err(plot_error)?;
        for (renderer, colour) in [("pt", BLUE), ("reference", RED)] {
            let line: Vec<(f64, f64)> = points
                .iter()
                .filter(|p| p.renderer == renderer)
                .map(|p| (p.seconds.max(1e-4), p.relative_l2))
                .collect();
            chart
                .draw_series(LineSeries::new(line.clone(), colour.stroke_width(2)))
                .map_err(plot_error)?
                .label(renderer)
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 16, y)], colour));
            chart
                .draw_series(line.iter().map(|p| Circle::new(*p, 3, colour.filled())))
                .map_err(plot_error)?;
        }
        chart
            .configure_series_labels()
            .border_style(BLACK)
            .background_style(WHITE.mix(0.8))
            .draw()
            .map_err(plot_error)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::median;

    #[test]
    fn the_clock_median_is_the_frame_the_run_spends_its_middle_in() {
        // 30 frames of 80 ms converging (2.4 s of clock), then 48 held frames of 2 ms, each
        // taking a sensor period (1.6 s): the plain median is a held frame, the clock's a
        // converging one.
        let mut times = vec![80.0; 30];
        times.extend([2.0; 48]);
        assert_eq!(median(&mut times.clone()), 2.0);
        assert_eq!(clock_median_ms(&times), 80.0);
        // Frames within the sensor period all weigh alike: the plain median.
        let even = [3.0, 1.0, 2.0, 5.0, 4.0];
        assert_eq!(clock_median_ms(&even), 3.0);
        assert!(clock_median_ms(&[]).is_nan());
    }
}
