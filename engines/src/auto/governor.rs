//! The `auto` engine's decisions, apart from any GPU: per candidate (an engine with parameters)
//! a predicted error from the scene's features and a measured cost per frame, and which
//! candidate to run, with hysteresis.
//!
//! **Predicted error.** Δ has four parts ([`SceneFeatures`]): the shadow S, the object's
//! bleeding B, the real indirect light it hides O, and its glossy reflection G. A rasterising
//! engine gets each part wrong by a share of its own ([`ErrorModel::Raster`]): the shadow by
//! its edges (pixel centres while moving; converged over sub-pixel offsets while still) and,
//! under an environment map, by how coarsely it cuts the map into lights; the indirect parts by
//! how much of them it models (1 for the direct-light engines). With the parts independent,
//! e² = Σ (share · part)² / Σ part² ([`candidates`] says where the shares come from); while the
//! camera is still, the edges' share falls as 1/√frames over the frames the horizon holds
//! ([`Settings::horizon_ms`], at the sensor's rate or the engine's own, 32 at most). `pt` has no
//! bias: its error is its noise, k / √n for n samples per pixel, with k measured from its own
//! standard error while it runs (a prior before), and n the samples it fits into the budget per
//! frame, times the frames of the horizon while the camera is still (its means accumulate), or
//! once while it moves.
//!
//! **Cost.** The frame time of each candidate, tracked per motion state (a still scene lets
//! engines keep work between frames) as the median of its last frames, first measured by a
//! short probe. A candidate whose cost is not known yet is probed only when it would be chosen
//! were it to fit, only when the cost ratios in `ErrorModel::relative_cost` (lavapipe's,
//! a rough prior) do not put it far over the budget. A candidate counts as measured after
//! [`PROBE_FRAMES`] steady frames. A rasteriser's cost is estimated from a measured
//! rasteriser's, so with none measured the cheapest is measured first, and with the ratios'
//! spread only as far as the measured rasterisers bear it out (`ratio_fidelity`; where only the
//! unchecked ratios keep a winner out, one more rasteriser is measured to check them,
//! `calibration_probe`). `pt` measures its own and is probed as soon as it would win; with it
//! alone measured, the rasterisers are estimated from its cost per sample. `pt` fills whatever
//! budget it is given (it traces a share of a sample per pixel where a whole one does not fit),
//! so it costs its budget wherever its least step fits. Of the candidates clearly more accurate
//! the most accurate is probed first; of those that tie on error and are estimated cheaper,
//! the cheapest; no rasteriser where the cheapest was measured over the budget
//! (`priced_out_by_the_cheapest`); a probe due when another ends starts at once.
//!
//! **Choice.** Among the candidates that fit the budget, the lowest predicted error, where
//! errors within [`TIE`] count as equal and the cheaper wins (so a shadow-only scene gets the
//! cheapest shadow engine); with `max_error`, the cheapest that is predicted to meet it. None
//! fits: the cheapest. **Hysteresis**: a switch needs a predicted error lower by [`MARGIN`], or
//! a cost lower by [`COST_MARGIN`] at an error within [`TIE`] (or under `max_error`), and [`MIN_DWELL`] frames on the current
//! candidate, unless the current one has been over budget for [`OVER_BUDGET_FRAMES`] frames. A
//! probe runs its candidate for [`PROBE_FRAMES`] steady frames (after [`WARM_UP_MS`], which
//! no cost counts; a candidate measured over the budget is probed again after
//! [`REPROBE_FRAMES`]); then the choice is made afresh
//! (a probe measures, it does not decide).

use serde::Serialize;
use serde_json::{Map, Value};

use super::features::SceneFeatures;
use crate::pt::TILE_PHASES;

/// Errors within 10 % (relative, and 0.002 absolute) of each other count as equal: about the
/// error model's own spread on the five scenes it was fitted to (rms of the log error 0.06–0.16
/// per engine, 0.25–0.36 for `dir`, whose spot_bleed the model cannot hold; docs/ALGORITHMS.md).
pub const TIE: f64 = 0.10;
/// The absolute part of a tie and of a margin.
const SLACK: f64 = 0.002;
/// A switch for accuracy needs a predicted error 15 % (and 0.002) lower.
pub const MARGIN: f64 = 0.15;
/// A switch for cost (to a candidate as accurate, or under `max_error`) needs one 20 % cheaper.
pub const COST_MARGIN: f64 = 0.20;
/// Frames on a candidate before another switch (except when over budget).
pub const MIN_DWELL: u32 = 10;
/// Frames over budget (by 10 %) that force a switch to one that fits.
pub const OVER_BUDGET_FRAMES: u32 = 3;
/// A candidate estimated at more than this many budgets is not probed.
const PROBE_LIMIT: f64 = 1.5;
/// A rasteriser the cost ratios put more than this far (relative) from the scale's checks how
/// far the ratios hold ([`Governor::ratio_checks`]); one nearer says too little.
const RATIO_CHECK: f64 = 0.25;
/// The warm-up after a switch, whose frames are not the candidate's cost: the first frame
/// (it allocates and uploads), then frames until [`WARM_UP_MS`] of rendering or
/// [`WARM_UP_FRAMES`] frames, whichever comes first. On lavapipe the first frames still run
/// slow (measured on spot_bleed at 160 × 120: `pt` 64, 47, 43, then 27–41 ms; `dir` 64 VPLs
/// 100, then 17–30 ms); counting them priced `pt` out of a 33 ms budget it fits. A candidate
/// whose frames take a second warms up in one; one whose frames take a millisecond, in three.
pub const WARM_UP_MS: f64 = 150.0;
/// See [`WARM_UP_MS`].
pub const WARM_UP_FRAMES: u32 = 3;
/// Steady frames (after the warm-up) a probe measures.
pub const PROBE_FRAMES: u32 = 3;
/// Frames after which a candidate measured over the budget (but within `PROBE_LIMIT`) that
/// would win were it to fit is probed again: ten seconds at 30 Hz. The adapter's speed drifts
/// (a shared machine's phases, a GPU's clocks, another process), and a cost measured in a slow
/// spell would otherwise keep the best candidate out for good.
pub const REPROBE_FRAMES: u64 = 300;
/// pt's noise at one sample per pixel (relative L2 of Δ) before it has run: the lowest of the
/// five scenes' (0.4 on glossy_floor; about 3 on desk_box), so that pt is probed wherever it
/// could win; its own measurement replaces it once it has traced [`PT_PROBE_SAMPLES`].
const PT_NOISE_PRIOR: f64 = 0.4;
/// Samples per pixel a probe of `pt` traces before its noise counts as measured.
pub const PT_PROBE_SAMPLES: f64 = 16.0;
/// ... or this many frames, whichever comes first.
const PT_PROBE_FRAMES: u32 = 30;

/// A candidate's last [`FrameTimes::KEPT`] frame times: their median is its cost, robust to
/// slow frames from outside (a shared machine: bursts of 4–5 frames at 1.5–2.5× were seen on
/// lavapipe, which a median of 9 let price a fitting `pt` out of its budget) and to a frame
/// that rebuilt something. Half a second at 30 Hz; a sustained overload switches sooner, by
/// [`OVER_BUDGET_FRAMES`].
#[derive(Debug, Clone, Default)]
struct FrameTimes(std::collections::VecDeque<f64>);

impl FrameTimes {
    const KEPT: usize = 15;

    fn push(&mut self, ms: f64) {
        if self.0.len() == Self::KEPT {
            self.0.pop_front();
        }
        self.0.push_back(ms);
    }

    fn median(&self) -> Option<f64> {
        let mut sorted: Vec<f64> = self.0.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        sorted.get(sorted.len() / 2).copied()
    }
}

/// Whether the picture's inputs held since the last frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Motion {
    Moving,
    Still,
}

impl Motion {
    fn index(self) -> usize {
        match self {
            Motion::Moving => 0,
            Motion::Still => 1,
        }
    }
}

/// How a candidate's error follows from the scene's features.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ErrorModel {
    /// Shares of each part of Δ a rasterising engine gets wrong.
    Raster {
        /// The shadow of point, spot and directional lights, converged over still frames (its
        /// edges averaged over the pixel's area).
        shadow: f64,
        /// The shadow under an environment map, which the engine cuts into a few lights.
        shadow_environment: f64,
        bleeding: f64,
        occlusion: f64,
        glossy: f64,
        /// Frame cost relative to `differential` (moving, still), on lavapipe at 160 × 120.
        relative_cost: [f64; 2],
        /// The cost is an environment map's: without one the engine renders as
        /// `differential` does, at its cost (`ibl`).
        environment_cost: bool,
    },
    /// `pt`: unbiased, noise only. Cost relative to `differential` of one sample per pixel.
    PathTraced { relative_cost: [f64; 2] },
}

impl ErrorModel {
    /// The cost relative to `differential` in `motion`, on a scene with or without an
    /// `environment` map.
    fn relative_cost(&self, motion: Motion, environment: bool) -> f64 {
        match self {
            ErrorModel::Raster {
                environment_cost: true,
                ..
            } if !environment => 1.0,
            ErrorModel::Raster { relative_cost, .. } | ErrorModel::PathTraced { relative_cost } => {
                relative_cost[motion.index()]
            }
        }
    }
}

/// One engine with parameters the governor may run.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// The engine and its parameters, as `relightd bench` labels a setting.
    pub label: String,
    pub engine: &'static str,
    pub params: Map<String, Value>,
    pub model: ErrorModel,
}

impl Candidate {
    pub fn new(engine: &'static str, params: Value, model: ErrorModel) -> Self {
        let params = params.as_object().cloned().unwrap_or_default();
        let label = std::iter::once(engine.to_owned())
            .chain(
                params
                    .iter()
                    .map(|(k, v)| format!("{k}={}", v.to_string().trim_matches('"'))),
            )
            .collect::<Vec<_>>()
            .join(" ");
        Self {
            label,
            engine,
            params,
            model,
        }
    }

    pub fn is_path_traced(&self) -> bool {
        matches!(self.model, ErrorModel::PathTraced { .. })
    }
}

/// What pixel-centre sampling adds to a rasterising engine's shadow error while the camera
/// moves (frames are not averaged): the bench's centre-against-area error on the five scenes.
const EDGE_MOVING: f64 = 0.20;
/// The sensor's frame period: frames come no faster (30 Hz).
pub const SENSOR_PERIOD_MS: f64 = 1000.0 / 30.0;
/// Still frames the rasterisers average at most (their `accumulate` default).
const ACCUMULATED_FRAMES: f64 = 32.0;

/// The candidates `auto` chooses from: every engine that relights at its defaults, `dir` also
/// with a quarter of its VPLs, and `pt` (whose budget the runner sets). Without an environment
/// map `ibl` predicts as `differential`, so it is never probed for accuracy there.
///
/// The shares are fitted (least squares in log error) to the still errors measured on the
/// project's five scenes (`relightd bench`'s converged Δ: 32 still frames against the
/// pixel-area reference; the indirect engines' at stop 54, bleeding and occlusion bounded below
/// at 0.1), given their features: `differential` comes out near 1 on bleeding and occlusion, as
/// an engine that models no indirect light must. Five scenes fit these few numbers only roughly
/// (docs/ALGORITHMS.md gives the residuals), so a scene unlike them can mislead the choice
/// among rasterisers, never the budget. The relative costs are lavapipe's frame times at
/// 160 × 120, each over `differential`'s on the same scene, medians over the five scenes
/// (`relightd bench --frames 5`: moving, `median_ms`, every input changed; still, `static_ms`,
/// frames being accumulated; `pt` at one sample per pixel, `spp=1`). Re-measured at stop 45,
/// after `differential`'s frame had halved (the ratios had been 15 and 17 for `dlpv` and
/// `dvct` moving, 12 for `dir`, 2 for `pt`).
pub fn candidates() -> Vec<Candidate> {
    let raster = |shadow, shadow_environment, bleeding, occlusion, glossy, relative_cost| {
        ErrorModel::Raster {
            shadow,
            shadow_environment,
            bleeding,
            occlusion,
            glossy,
            relative_cost,
            environment_cost: false,
        }
    };
    vec![
        Candidate::new(
            "differential",
            serde_json::json!({}),
            raster(0.08, 0.16, 1.0, 1.0, 1.0, [1.0, 1.0]),
        ),
        Candidate::new(
            "ibl",
            serde_json::json!({}),
            // Measured without a map, `ibl` costs what `differential` does, and read as a
            // check of the ratios it disbelieved them all: `dir` (65 ms a frame) was then
            // probed at 10 ms on spot_bleed.
            ErrorModel::Raster {
                shadow: 0.08,
                shadow_environment: 0.10,
                bleeding: 1.0,
                occlusion: 1.0,
                glossy: 1.0,
                relative_cost: [1.5, 1.3],
                environment_cost: true,
            },
        ),
        Candidate::new(
            "dlpv",
            serde_json::json!({}),
            raster(0.08, 0.11, 0.41, 0.54, 1.0, [9.0, 2.3]),
        ),
        Candidate::new(
            "dvct",
            serde_json::json!({}),
            raster(0.08, 0.13, 0.1, 0.66, 0.7, [11.0, 15.0]),
        ),
        Candidate::new(
            "dir",
            serde_json::json!({ "vpl_count": 64 }),
            raster(0.08, 0.10, 0.1, 0.56, 1.0, [24.0, 34.0]),
        ),
        Candidate::new(
            "dir",
            serde_json::json!({}),
            raster(0.08, 0.10, 0.1, 0.45, 1.0, [72.0, 123.0]),
        ),
        Candidate::new(
            "pt",
            serde_json::json!({}),
            ErrorModel::PathTraced {
                relative_cost: [9.0, 13.0],
            },
        ),
    ]
}

/// What the governor knows of one candidate now.
#[derive(Debug, Clone, Serialize)]
pub struct Assessment {
    pub candidate: String,
    pub predicted_error: f64,
    /// Measured frame time in the current motion state; `None` before it has run in it.
    pub cost_ms: Option<f64>,
    /// An estimate from the cost ratios when not measured.
    pub estimated_cost_ms: Option<f64>,
    pub fits: Option<bool>,
}

/// What to do next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    Stay,
    /// Run this candidate from the next frame on.
    Switch(usize),
    /// Run this candidate for a few frames to measure its cost.
    Probe(usize),
}

/// The budget and the target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    pub budget_ms: f64,
    pub max_error: Option<f64>,
    /// How long a still camera is expected to stay still, milliseconds: what accumulates
    /// over frames (`pt`'s samples, the rasterisers' sub-pixel edges) is judged at this age.
    pub horizon_ms: f64,
}

/// The governor's state.
#[derive(Debug)]
pub struct Governor {
    candidates: Vec<Candidate>,
    /// Recent frame times per candidate, per motion state.
    costs: Vec<[FrameTimes; 2]>,
    /// The frame (counted by [`Governor::observe`]) each of those was last measured on.
    measured_on: Vec<[u64; 2]>,
    frame: u64,
    /// Candidates that failed to build (left out from then on).
    unavailable: Vec<bool>,
    settings: Settings,
    features: SceneFeatures,
    /// `pt`: its noise at one sample per pixel, and its cost per sample per pixel (ms).
    pt_noise: Option<f64>,
    pt_ms_per_spp: FrameTimes,
    /// `pt`'s samples per pixel after its last frame.
    pt_samples: f64,
    /// `pt` was probed in this motion state (its noise may stay unmeasured: one sample per
    /// frame of a moving camera gives no variance).
    pt_probed: [bool; 2],
    current: usize,
    frames_on_current: u32,
    over_budget: u32,
    /// The candidate being probed (switched to, or waiting for its build), and its steady
    /// frames so far.
    probing: Option<(usize, u32)>,
    switches: u64,
    reason: String,
}

impl Governor {
    pub fn new(candidates: Vec<Candidate>, current: usize, settings: Settings) -> Self {
        let n = candidates.len();
        Self {
            candidates,
            costs: vec![[FrameTimes::default(), FrameTimes::default()]; n],
            measured_on: vec![[0; 2]; n],
            frame: 0,
            unavailable: vec![false; n],
            settings,
            features: SceneFeatures::default(),
            pt_noise: None,
            pt_ms_per_spp: FrameTimes::default(),
            pt_samples: 0.0,
            pt_probed: [false; 2],
            current,
            frames_on_current: 0,
            over_budget: 0,
            probing: None,
            switches: 0,
            reason: "starting on the cheapest engine".into(),
        }
    }

    pub fn candidates(&self) -> &[Candidate] {
        &self.candidates
    }

    pub fn current(&self) -> usize {
        self.current
    }

    pub fn settings(&self) -> Settings {
        self.settings
    }

    pub fn features(&self) -> &SceneFeatures {
        &self.features
    }

    pub fn switches(&self) -> u64 {
        self.switches
    }

    pub fn reason(&self) -> &str {
        &self.reason
    }

    pub fn set_settings(&mut self, settings: Settings) {
        self.settings = settings;
    }

    pub fn set_features(&mut self, features: SceneFeatures) {
        self.features = features;
    }

    /// Forget every measured cost (the image size changed: costs scale with it).
    pub fn forget_costs(&mut self) {
        for cost in &mut self.costs {
            *cost = [FrameTimes::default(), FrameTimes::default()];
        }
        self.pt_ms_per_spp = FrameTimes::default();
        self.pt_probed = [false; 2];
    }

    /// A candidate could not be built: never choose it.
    pub fn mark_unavailable(&mut self, candidate: usize) {
        if let Some(flag) = self.unavailable.get_mut(candidate) {
            *flag = true;
        }
        if self.probing.is_some_and(|(c, _)| c == candidate) {
            self.probing = None;
        }
    }

    /// The candidate being probed, if any.
    pub fn probing(&self) -> Option<usize> {
        self.probing.map(|(c, _)| c)
    }

    /// `candidate` rendered a frame in `motion` in `ms`. `path_samples` and `estimated_error`
    /// are what the frame reported (`pt`'s samples per pixel so far, and its own error
    /// estimate); `samples_added` how many it traced this frame. `steady`: past the
    /// [`WARM_UP_MS`] after a switch, so it counts towards the cost.
    pub fn observe(
        &mut self,
        candidate: usize,
        motion: Motion,
        ms: f64,
        steady: bool,
        pt: Option<PtFrame>,
    ) {
        self.frame += 1;
        if candidate == self.current {
            self.frames_on_current = self.frames_on_current.saturating_add(1);
            let over = ms > 1.1 * self.settings.budget_ms;
            self.over_budget = if over && steady {
                self.over_budget + 1
            } else {
                0
            };
        }
        if !(steady && ms.is_finite()) {
            return;
        }
        if let Some((probed, frames)) = &mut self.probing
            && *probed == candidate
        {
            *frames += 1;
        }
        if let Some(cost) = self.costs.get_mut(candidate) {
            cost[motion.index()].push(ms);
            self.measured_on[candidate][motion.index()] = self.frame;
        }
        if let Some(pt) = pt {
            self.pt_samples = pt.path_samples;
            if pt.samples_added > 0.0 {
                self.pt_ms_per_spp.push(ms / pt.samples_added);
            }
            if let Some(error) = pt.estimated_error.filter(|e| e.is_finite())
                && pt.path_samples >= 4.0
            {
                let noise = error * pt.path_samples.sqrt();
                self.pt_noise = Some(self.pt_noise.map_or(noise, |old| 0.7 * old + 0.3 * noise));
            }
        }
    }

    /// The predicted error of `candidate` for this scene in `motion`.
    pub fn predicted_error(&self, candidate: usize, motion: Motion) -> f64 {
        let f = &self.features;
        match self.candidates[candidate].model {
            ErrorModel::Raster {
                shadow,
                shadow_environment,
                bleeding,
                occlusion,
                glossy,
                ..
            } => {
                let total = f.total();
                if total <= 0.0 {
                    return 0.0;
                }
                let converged = if f.environment {
                    shadow_environment
                } else {
                    shadow
                };
                // Pixel-centre edges average out over the still frames the horizon holds (32 at
                // most: the engines' `accumulate`), at the sensor's rate or the engine's own.
                let frames = match motion {
                    Motion::Moving => 1.0,
                    Motion::Still => {
                        let frame_ms = self
                            .cost(candidate, motion)
                            .or_else(|| self.estimated_cost(candidate, motion))
                            .unwrap_or(SENSOR_PERIOD_MS)
                            .max(SENSOR_PERIOD_MS);
                        (self.settings.horizon_ms / frame_ms).clamp(1.0, ACCUMULATED_FRAMES)
                    }
                };
                let shadow = converged.hypot(EDGE_MOVING / frames.sqrt());
                ((shadow * f.shadow).powi(2)
                    + (bleeding * f.bleeding).powi(2)
                    + (occlusion * f.occlusion).powi(2)
                    + (glossy * f.glossy).powi(2))
                .sqrt()
                    / total
            }
            ErrorModel::PathTraced { .. } => {
                if f.total() <= 0.0 {
                    return 0.0;
                }
                // Before pt has run, its cost per sample from the ratios.
                let per_spp = self
                    .pt_ms_per_spp
                    .median()
                    .or_else(|| self.estimated_cost(candidate, motion))
                    .unwrap_or(self.settings.budget_ms)
                    .max(1e-6);
                // pt traces a share of a sample per pixel where a whole one does not fit.
                let per_frame =
                    (self.settings.budget_ms / per_spp).max(1.0 / f64::from(TILE_PHASES));
                let samples = match motion {
                    Motion::Moving => per_frame,
                    // Frames come no faster than the sensor's, each with its budget's samples.
                    Motion::Still => {
                        let frame_ms = self.settings.budget_ms.max(SENSOR_PERIOD_MS);
                        per_frame * (self.settings.horizon_ms / frame_ms).max(1.0)
                    }
                };
                self.pt_noise.unwrap_or(PT_NOISE_PRIOR) / samples.sqrt()
            }
        }
    }

    /// Measured cost of `candidate` in `motion`. `pt` costs its budget (it fills it with
    /// samples) once its least step, a sample for one tile phase, is known to fit, else that
    /// step's cost.
    fn cost(&self, candidate: usize, motion: Motion) -> Option<f64> {
        if self.candidates[candidate].is_path_traced() {
            let step = self.pt_step_ms()?;
            return Some(if step <= self.settings.budget_ms {
                self.settings.budget_ms
            } else {
                step
            });
        }
        self.costs[candidate][motion.index()].median()
    }

    /// What `pt`'s least step costs: a sample per pixel for one tile phase.
    fn pt_step_ms(&self) -> Option<f64> {
        Some(self.pt_ms_per_spp.median()? / f64::from(TILE_PHASES))
    }

    /// Whether the governor knows what it needs of `candidate` in `motion`: its cost, and for
    /// `pt` its noise (or it was probed here and its noise could not be measured).
    fn measured(&self, candidate: usize, motion: Motion) -> bool {
        if self.candidates[candidate].is_path_traced() {
            return self.pt_probed[motion.index()]
                || (self.cost(candidate, motion).is_some() && self.pt_noise.is_some());
        }
        // Over as many steady frames as a probe measures: a fresh engine's first frames run
        // slow on lavapipe (`differential` read 13.8 ms against a 10 ms budget over one frame,
        // 7.4 ms later, and lost a budget it fits).
        self.costs[candidate][motion.index()].0.len() >= PROBE_FRAMES as usize
    }

    /// Whether `candidate` was measured over the budget in `motion` more than
    /// [`REPROBE_FRAMES`] ago: worth measuring again where it would win.
    fn stale(&self, candidate: usize, motion: Motion) -> bool {
        self.cost(candidate, motion)
            .is_some_and(|ms| ms > self.settings.budget_ms)
            && self.frame - self.measured_on[candidate][motion.index()] > REPROBE_FRAMES
    }

    /// A cost from the ratios to a measured candidate, for one not measured yet: the measured
    /// cost, plus the ratios' excess over it as far as [`Self::ratio_fidelity`] bears it out.
    /// With no rasteriser measured, a rasteriser's cost follows from `pt`'s measured cost of a
    /// sample per pixel by the ratios alone: `pt` is probed first wherever its prior wins, and
    /// without this a rasteriser tying it on error (and a tenth its cost at a 1000 ms budget)
    /// had no cost to be found cheaper by, and was never measured.
    fn estimated_cost(&self, candidate: usize, motion: Motion) -> Option<f64> {
        let Some(known) = self.scale(motion) else {
            let pt = (0..self.candidates.len()).find(|&c| self.candidates[c].is_path_traced())?;
            let per_spp = self.pt_ms_per_spp.median()?;
            return (candidate != pt).then(|| per_spp * self.ratio(candidate, pt, motion));
        };
        let ms = self.cost(known, motion)?;
        let ratio = self.ratio(candidate, known, motion);
        Some(ms * (1.0 + (ratio - 1.0) * self.ratio_fidelity(known, motion)))
    }

    /// `candidate`'s cost over `known`'s by the cost ratios.
    fn ratio(&self, candidate: usize, known: usize, motion: Motion) -> f64 {
        self.relative_cost(candidate, motion) / self.relative_cost(known, motion)
    }

    /// `candidate`'s cost relative to `differential` by the ratios, on this scene.
    fn relative_cost(&self, candidate: usize, motion: Motion) -> f64 {
        self.candidates[candidate]
            .model
            .relative_cost(motion, self.features.environment)
    }

    /// Whether `candidate`, measured, would check the cost ratios' spread against `known`: a
    /// rasteriser they put more than [`RATIO_CHECK`] from it.
    fn would_check(&self, candidate: usize, known: usize, motion: Motion) -> bool {
        candidate != known
            && !self.candidates[candidate].is_path_traced()
            && (self.ratio(candidate, known, motion) - 1.0).abs() > RATIO_CHECK
    }

    /// The measured rasterisers that check the ratios' spread against `known`.
    fn ratio_checks(&self, known: usize, motion: Motion) -> impl Iterator<Item = usize> + '_ {
        (0..self.candidates.len())
            .filter(move |&c| self.measured(c, motion) && self.would_check(c, known, motion))
    }

    /// How much of the cost ratios' difference from `known` the measured rasterisers showed:
    /// 1 where they cost what the ratios say (lavapipe's, whence the ratios), less where they
    /// cost more alike. On an H200 at 640 × 480 every rasteriser's frame is 3.5–5 ms, a fixed
    /// part of upload and read-back ahead of its passes, where the ratios then put `dir` at 12
    /// times `differential` (123 since): estimated so, it was never probed at a 5 ms budget it
    /// fitted. The largest
    /// showing of any check (the ratios in full until there is one), within 0..=1.
    fn ratio_fidelity(&self, known: usize, motion: Motion) -> f64 {
        let Some(base) = self.cost(known, motion) else {
            return 1.0;
        };
        self.ratio_checks(known, motion)
            .filter_map(|c| {
                Some((self.cost(c, motion)? / base - 1.0) / (self.ratio(c, known, motion) - 1.0))
            })
            .reduce(f64::max)
            .map_or(1.0, |shown| shown.clamp(0.0, 1.0))
    }

    /// With nothing to check the ratios' spread by ([`Self::ratio_checks`]): of the unmeasured
    /// rasterisers that would be a check, the one the ratios put dearest within reach of the
    /// budget.
    fn calibration_probe(&self, motion: Motion) -> Option<usize> {
        let known = self.scale(motion)?;
        if self.ratio_checks(known, motion).next().is_some() {
            return None;
        }
        let ratio = |c: usize| self.ratio(c, known, motion);
        (0..self.candidates.len())
            .filter(|&c| c != self.current && !self.unavailable[c] && !self.measured(c, motion))
            .filter(|&c| !self.priced_out_by_the_cheapest(c, motion))
            .filter(|&c| self.would_check(c, known, motion))
            .filter(|&c| {
                self.estimated_cost(c, motion)
                    .is_some_and(|ms| ms <= PROBE_LIMIT * self.settings.budget_ms)
            })
            .max_by(|&a, &b| ratio(a).total_cmp(&ratio(b)))
    }

    /// The measured rasteriser the others' costs are scaled from.
    fn scale(&self, motion: Motion) -> Option<usize> {
        (0..self.candidates.len())
            .find(|&c| !self.candidates[c].is_path_traced() && self.measured(c, motion))
    }

    /// The available rasteriser the cost ratios call cheapest: where `auto` starts, and what
    /// is measured first when nothing fits or a scale is wanted.
    fn cheapest_by_ratio(&self, motion: Motion) -> Option<usize> {
        (0..self.candidates.len())
            .filter(|&c| !self.unavailable[c] && !self.candidates[c].is_path_traced())
            .min_by(|&a, &b| {
                self.relative_cost(a, motion)
                    .total_cmp(&self.relative_cost(b, motion))
            })
    }

    /// Whether `candidate`, a rasteriser, cannot fit the budget because the rasteriser the
    /// ratios call cheapest was measured over it (within [`REPROBE_FRAMES`]): every
    /// rasteriser does `differential`'s work (G-buffers, shadow maps, the composite) and more.
    /// On window_env at 10 ms `differential` read 13 ms, `dlpv` measured alike made the
    /// ratios' spread unbelieved, and `dlpv` and `ibl` were probed in turn, frames `pt`'s
    /// samples did not get (28 against the fixed run's 40).
    fn priced_out_by_the_cheapest(&self, candidate: usize, motion: Motion) -> bool {
        let Some(cheapest) = self.cheapest_by_ratio(motion) else {
            return false;
        };
        candidate != cheapest
            && !self.candidates[candidate].is_path_traced()
            && self.measured(cheapest, motion)
            && self.frame - self.measured_on[cheapest][motion.index()] <= REPROBE_FRAMES
            && self
                .cost(cheapest, motion)
                .is_some_and(|ms| ms > self.settings.budget_ms)
    }

    /// The least frame a candidate not measured yet is estimated to cost: `pt`'s least step
    /// (a tile phase's share of a sample), another's frame.
    fn estimated_least_cost(&self, candidate: usize, motion: Motion) -> Option<f64> {
        let ms = self.estimated_cost(candidate, motion)?;
        Some(if self.candidates[candidate].is_path_traced() {
            ms / f64::from(TILE_PHASES)
        } else {
            ms
        })
    }

    /// Every candidate as the governor sees it now.
    pub fn assess(&self, motion: Motion) -> Vec<Assessment> {
        (0..self.candidates.len())
            .map(|c| {
                let cost = self.cost(c, motion);
                Assessment {
                    candidate: self.candidates[c].label.clone(),
                    predicted_error: self.predicted_error(c, motion),
                    cost_ms: cost,
                    estimated_cost_ms: cost
                        .is_none()
                        .then(|| self.estimated_cost(c, motion))
                        .flatten(),
                    fits: cost.map(|ms| ms <= self.settings.budget_ms),
                }
            })
            .collect()
    }

    /// The candidate to run among those whose cost is known, and why.
    fn choose(&self, motion: Motion) -> (usize, String) {
        let budget = self.settings.budget_ms;
        // pt's error is only known once its noise is (the prior is for probing).
        let known: Vec<(usize, f64, f64)> = (0..self.candidates.len())
            .filter(|&c| !self.unavailable[c])
            .filter(|&c| {
                if self.candidates[c].is_path_traced() {
                    self.pt_noise.is_some()
                } else {
                    self.measured(c, motion)
                }
            })
            .filter_map(|c| Some((c, self.predicted_error(c, motion), self.cost(c, motion)?)))
            .collect();
        let cheapest =
            |set: &[(usize, f64, f64)]| set.iter().copied().min_by(|a, b| a.2.total_cmp(&b.2));
        let fitting: Vec<_> = known.iter().copied().filter(|k| k.2 <= budget).collect();
        let state = match motion {
            Motion::Moving => "moving",
            Motion::Still => "still",
        };
        if fitting.is_empty() {
            // Nothing measured fits: the cheapest rasteriser by the ratios while it is not
            // measured yet, else the cheapest measured.
            if let Some(c) = self
                .cheapest_by_ratio(motion)
                .filter(|&c| !self.measured(c, motion))
            {
                return (
                    c,
                    format!(
                        "nothing measured fits {budget:.0} ms ({state}): the cheapest by the cost ratios"
                    ),
                );
            }
            let Some((c, _, ms)) = cheapest(&known) else {
                return (self.current, "no candidate measured yet".into());
            };
            return (
                c,
                format!("nothing measured fits {budget:.0} ms ({state}): the cheapest, {ms:.1} ms"),
            );
        }
        if let Some(target) = self.settings.max_error {
            let meeting: Vec<_> = fitting.iter().copied().filter(|k| k.1 <= target).collect();
            if let Some((c, error, ms)) = cheapest(&meeting) {
                return (
                    c,
                    format!(
                        "the cheapest ({ms:.1} ms of {budget:.0}, {state}) predicted to meet \
                         max_error {target}: {error:.3}"
                    ),
                );
            }
        }
        let best = fitting.iter().map(|k| k.1).fold(f64::INFINITY, f64::min);
        let tied: Vec<_> = fitting
            .iter()
            .copied()
            .filter(|k| k.1 <= best * (1.0 + TIE) + SLACK)
            .collect();
        let (c, error, ms) = cheapest(&tied).expect("the best is among the tied");
        let why = if tied.len() > 1 {
            format!(
                "lowest predicted error ({error:.3}) within {budget:.0} ms ({state}), the \
                 cheapest of {} that tie: {ms:.1} ms",
                tied.len()
            )
        } else {
            format!(
                "lowest predicted error ({error:.3}) within {budget:.0} ms ({state}): {ms:.1} ms"
            )
        };
        (c, why)
    }

    /// What to do after this frame, with the scene in `motion`. `building`: a candidate is
    /// being built for a switch (no probe starts).
    pub fn decide(&mut self, motion: Motion, building: bool) -> Action {
        let mut probe_ended = false;
        if let Some((probed, frames)) = self.probing {
            // pt's noise is measured over its accumulating samples: while still, and only where
            // its least step fits the budget.
            let measuring_noise = self.candidates[probed].is_path_traced()
                && motion == Motion::Still
                && self
                    .pt_step_ms()
                    .is_none_or(|ms| ms <= self.settings.budget_ms)
                && self.pt_samples < PT_PROBE_SAMPLES
                && frames < PT_PROBE_FRAMES;
            // pt's cost is its budget once its step fits, and one steady frame that traced
            // the samples its noise needs has measured both: at a 1000 ms budget three would
            // have taken most of the time a still scene is judged at.
            let measured_pt = self.candidates[probed].is_path_traced()
                && frames >= 1
                && self.pt_samples >= PT_PROBE_SAMPLES;
            if probed != self.current || (frames < PROBE_FRAMES && !measured_pt) || measuring_noise
            {
                return Action::Stay;
            }
            // A probe is a measurement, not a decision: choose afresh, without hysteresis
            // (below), unless another probe is due, which starts at once: switching back to
            // the choice in between would cost a frame (a second of `pt`'s at 1000 ms).
            self.probing = None;
            probe_ended = true;
        }
        let (choice, why) = self.choose(motion);
        let current_error = self.predicted_error(self.current, motion);
        let over = self.over_budget >= OVER_BUDGET_FRAMES;
        // A candidate not measured yet that would win were it to fit, and that the cost ratios
        // do not put far over the budget: clearly more accurate, or a rasteriser as accurate
        // (within a tie) and estimated clearly cheaper, as a switch would need. Without the
        // second, `dlpv`'s 7 ms still frame on desk_box, tying `dir`'s 64 VPLs at 19 ms on
        // error, was never measured at a 33 ms budget and `dir`'s 0.29 stood against its 0.22.
        let target = self.predicted_error(choice, motion);
        let choice_cost = self.cost(choice, motion);
        let ties_cheaper = |c: usize| {
            !self.candidates[c].is_path_traced()
                && self.predicted_error(c, motion) <= target * (1.0 + TIE) + SLACK
                && matches!(
                    (self.estimated_cost(c, motion), choice_cost),
                    (Some(then), Some(now)) if then < now * (1.0 - COST_MARGIN)
                )
        };
        let within_reach = |c: usize| {
            !self.priced_out_by_the_cheapest(c, motion)
                && self
                    .cost(c, motion)
                    .or_else(|| self.estimated_least_cost(c, motion))
                    .is_none_or(|ms| ms <= PROBE_LIMIT * self.settings.budget_ms)
        };
        let unmeasured: Vec<usize> = (0..self.candidates.len())
            .filter(|&c| {
                c != self.current
                    && !self.unavailable[c]
                    && (!self.measured(c, motion) || self.stale(c, motion))
            })
            .collect();
        let more_accurate: Vec<usize> = unmeasured
            .iter()
            .copied()
            .filter(|&c| self.predicted_error(c, motion) * (1.0 + TIE) + SLACK < target)
            .collect();
        let as_accurate_cheaper: Vec<usize> = unmeasured
            .iter()
            .copied()
            .filter(|&c| !more_accurate.contains(&c) && ties_cheaper(c))
            .collect();
        let winners: Vec<usize> = more_accurate
            .iter()
            .chain(&as_accurate_cheaper)
            .copied()
            .collect();
        // The most accurate of those clearly more accurate; else, of those as accurate, the
        // cheapest, whose cost then rules the dearer out (on desk_box at 1000 ms `dir` was
        // probed before `dlpv`, and the scene was judged in `dir`'s warm-up).
        let probe = more_accurate
            .iter()
            .copied()
            .filter(|&c| within_reach(c))
            .min_by(|&a, &b| {
                self.predicted_error(a, motion)
                    .total_cmp(&self.predicted_error(b, motion))
            })
            .or_else(|| {
                as_accurate_cheaper
                    .iter()
                    .copied()
                    .filter(|&c| within_reach(c))
                    .filter_map(|c| Some((c, self.estimated_cost(c, motion)?)))
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .map(|(c, _)| c)
            })
            .or_else(|| {
                // Only the ratios, unchecked, keep a winner out of reach: measure the rasteriser
                // they put dearest within reach, so the next estimates know how far to believe them.
                winners
                    .iter()
                    .any(|&c| !self.candidates[c].is_path_traced())
                    .then(|| self.calibration_probe(motion))
                    .flatten()
            });
        // A rasteriser's cost is estimated from a measured one's: with none measured, the
        // cheapest is measured first, as the scale; the running candidate is measured by
        // running. `pt` measures its own, and is probed as soon as it would win (every frame
        // before it starts is one its means do not hold).
        let probe = match probe {
            Some(c) if !self.candidates[c].is_path_traced() && self.scale(motion).is_none() => self
                .cheapest_by_ratio(motion)
                .filter(|&c| c != self.current),
            other => other,
        };
        if !building && let Some(candidate) = probe {
            let why = if self.stale(candidate, motion) {
                "over the budget when last measured"
            } else {
                "cost not measured yet"
            };
            self.probing = Some((candidate, 0));
            // Measured afresh: the probe's frames are its cost.
            self.costs[candidate][motion.index()] = FrameTimes::default();
            if self.candidates[candidate].is_path_traced() {
                self.pt_probed[motion.index()] = true;
                self.pt_ms_per_spp = FrameTimes::default();
            }
            self.reason = format!(
                "probing {}: predicted error {:.3}, {why}",
                self.candidates[candidate].label,
                self.predicted_error(candidate, motion)
            );
            return Action::Probe(candidate);
        }
        if choice == self.current {
            self.reason = why;
            return Action::Stay;
        }
        let choice_error = self.predicted_error(choice, motion);
        let cheaper = matches!(
            (self.cost(self.current, motion), self.cost(choice, motion)),
            (Some(now), Some(then)) if then < now * (1.0 - COST_MARGIN)
        );
        let better = match self.settings.max_error {
            Some(target) if current_error <= target => cheaper,
            // As accurate (within a tie) and clearly cheaper, or clearly more accurate.
            _ => {
                (cheaper && choice_error <= current_error * (1.0 + TIE) + SLACK)
                    || choice_error < current_error * (1.0 - MARGIN) - SLACK
            }
        };
        let current_fits = self
            .cost(self.current, motion)
            .is_some_and(|ms| ms <= self.settings.budget_ms);
        let dwelt = self.frames_on_current >= MIN_DWELL;
        if probe_ended || (!building && (over || (dwelt && (better || !current_fits)))) {
            self.reason = why;
            return Action::Switch(choice);
        }
        Action::Stay
    }

    /// The runner switched to `candidate`.
    pub fn switched(&mut self, candidate: usize) {
        if candidate != self.current {
            self.switches += 1;
        }
        self.current = candidate;
        self.frames_on_current = 0;
        self.over_budget = 0;
    }

    /// Whether the choice has settled: no probe under way and none due.
    pub fn settled(&self) -> bool {
        self.probing.is_none()
    }
}

/// What a `pt` frame reported, for [`Governor::observe`].
#[derive(Debug, Clone, Copy)]
pub struct PtFrame {
    pub path_samples: f64,
    pub samples_added: f64,
    pub estimated_error: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    const DIFFERENTIAL: usize = 0;
    const IBL: usize = 1;
    const DLPV: usize = 2;
    const DIR64: usize = 4;
    const DIR: usize = 5;
    const PT: usize = 6;

    fn features(shadow: f64, bleeding: f64, occlusion: f64) -> SceneFeatures {
        SceneFeatures {
            shadow,
            bleeding,
            occlusion,
            blocks_light: shadow > 0.0,
            ..SceneFeatures::default()
        }
    }

    /// A governor on `features` at `budget_ms` (2 s horizon, no `max_error`), running
    /// `differential`, nothing measured.
    fn fresh(features: SceneFeatures, budget_ms: f64) -> Governor {
        let mut governor = Governor::new(
            candidates(),
            DIFFERENTIAL,
            Settings {
                budget_ms,
                max_error: None,
                horizon_ms: 2000.0,
            },
        );
        governor.set_features(features);
        governor
    }

    /// `candidate` measured at `ms` a frame over a probe's steady frames, still.
    fn measure(governor: &mut Governor, candidate: usize, ms: f64) {
        for _ in 0..PROBE_FRAMES {
            governor.observe(candidate, Motion::Still, ms, true, None);
        }
    }

    /// A governor on `features` at `budget_ms` whose candidates' costs are all measured (still,
    /// ms): an earlier build's on lavapipe at 160 × 120, `pt` 40 ms per sample per pixel with
    /// noise 2.5.
    fn measured(features: SceneFeatures, budget_ms: f64) -> Governor {
        let mut governor = fresh(features, budget_ms);
        for (candidate, ms) in [5.0, 6.0, 6.0, 200.0, 20.0, 50.0].into_iter().enumerate() {
            measure(&mut governor, candidate, ms);
        }
        governor.observe(
            PT,
            Motion::Still,
            40.0,
            true,
            Some(PtFrame {
                path_samples: 16.0,
                samples_added: 1.0,
                estimated_error: Some(0.625),
            }),
        );
        governor
    }

    /// Run `decide` for `frames` frames on the current candidate, switching as told; the
    /// candidates switched to.
    fn run(governor: &mut Governor, motion: Motion, frames: u32) -> Vec<usize> {
        let mut switches = Vec::new();
        for _ in 0..frames {
            let current = governor.current();
            let ms = governor.cost(current, motion).unwrap_or(1.0);
            governor.observe(current, motion, ms, true, None);
            if let Action::Switch(c) | Action::Probe(c) = governor.decide(motion, false) {
                governor.switched(c);
                switches.push(c);
            }
        }
        switches
    }

    /// Run the probed `candidate` at `ms` a frame, its first [`WARM_UP_FRAMES`] flagged as
    /// warm-up as `Auto` flags them (`pt` tracing a sample a frame), until the governor acts:
    /// the action and the frames it took.
    fn probe(governor: &mut Governor, candidate: usize, ms: f64) -> (Action, u32) {
        let mut frames = 0;
        loop {
            frames += 1;
            let pt = (candidate == PT).then_some(PtFrame {
                path_samples: f64::from(frames),
                samples_added: 1.0,
                estimated_error: Some(0.3),
            });
            governor.observe(candidate, Motion::Still, ms, frames > WARM_UP_FRAMES, pt);
            let action = governor.decide(Motion::Still, false);
            if action != Action::Stay {
                return (action, frames);
            }
            assert!(frames < 10, "{}", governor.reason());
        }
    }

    /// [`probe`] `candidate` at `ms`; where the choice made afresh switches, the decision on
    /// the candidate switched to.
    fn next_after_probe(governor: &mut Governor, candidate: usize, ms: f64) -> Action {
        match probe(governor, candidate, ms).0 {
            Action::Switch(c) => {
                governor.switched(c);
                governor.decide(Motion::Still, false)
            }
            action => action,
        }
    }

    #[test]
    fn a_shadow_only_scene_chooses_the_cheapest_shadow_engine() {
        // Every rasteriser predicts the same error on a shadow alone: the cheapest wins, and
        // nothing is switched to (pt fits 33 ms, but its noise is far above their error).
        let mut governor = measured(features(10.0, 0.0, 0.0), 33.0);
        let switches = run(&mut governor, Motion::Still, 40);
        assert!(switches.is_empty(), "{switches:?}: {}", governor.reason());
        assert_eq!(governor.current(), DIFFERENTIAL);
        assert!(
            governor.reason().contains("cheapest of"),
            "{}",
            governor.reason()
        );
        // Started on a dearer one that is no more accurate, it moves to the cheapest.
        let mut governor = measured(features(10.0, 0.0, 0.0), 33.0);
        governor.switched(DIR64);
        run(&mut governor, Motion::Still, 40);
        assert_eq!(governor.current(), DIFFERENTIAL);
    }

    #[test]
    fn a_strong_bleeding_scene_chooses_an_indirect_engine() {
        // Bleeding and occlusion: on bleeding alone `dir` and `dir` at 64 VPLs tie (both at
        // the shares' floor); the occlusion tells them apart.
        let bleeding = features(2.0, 6.0, 4.0);
        let mut governor = measured(bleeding, 33.0);
        run(&mut governor, Motion::Still, 40);
        assert_eq!(governor.current(), DIR64, "{}", governor.reason());
        let mut governor = measured(bleeding, 100.0);
        run(&mut governor, Motion::Still, 40);
        assert_eq!(governor.current(), DIR, "{}", governor.reason());
        // Two seconds of a still camera hold 2 such frames: pt's 50 samples only tie dir.
        let mut governor = measured(bleeding, 1000.0);
        run(&mut governor, Motion::Still, 40);
        assert_eq!(governor.current(), DIR, "{}", governor.reason());
        // Twenty seconds: its 500 samples pass every bias.
        governor.set_settings(Settings {
            horizon_ms: 20_000.0,
            ..governor.settings()
        });
        run(&mut governor, Motion::Still, 40);
        assert_eq!(governor.current(), PT, "{}", governor.reason());
        // The same budget with the camera moving: one frame's samples.
        assert!(
            governor.predicted_error(PT, Motion::Moving)
                > 3.0 * governor.predicted_error(PT, Motion::Still)
        );
    }

    #[test]
    fn max_error_takes_the_cheapest_that_meets_it() {
        let mut governor = measured(features(2.0, 6.0, 4.0), 1000.0);
        let target = governor.predicted_error(DIR64, Motion::Still) * 1.01;
        governor.set_settings(Settings {
            max_error: Some(target),
            ..governor.settings()
        });
        run(&mut governor, Motion::Still, 40);
        assert_eq!(governor.current(), DIR64, "{}", governor.reason());
    }

    #[test]
    fn unmeasured_candidates_that_would_win_are_probed_then_chosen_afresh() {
        let mut governor = fresh(features(2.0, 6.0, 4.0), 50.0);
        // Nothing measured: pt, the most promising, measures its own cost, so it is probed
        // at once.
        assert_eq!(governor.decide(Motion::Still, false), Action::Probe(PT));
        assert_eq!(
            governor.decide(Motion::Still, true),
            Action::Stay,
            "waits for its build"
        );
        governor.switched(PT);
        // Its sample costs 1.6 s: not even a tile phase's share of one (100 ms) fits, so its
        // noise is not worth measuring and the probe ends after its steady frames; the choice
        // is made afresh, without hysteresis: with nothing measured that fits, the cheapest
        // by the cost ratios.
        let (action, frames) = probe(&mut governor, PT, 1600.0);
        assert_eq!(
            action,
            Action::Switch(DIFFERENTIAL),
            "{}",
            governor.reason()
        );
        assert_eq!(frames, WARM_UP_FRAMES + PROBE_FRAMES);
        governor.switched(DIFFERENTIAL);
        // A rasteriser's cost is estimated from the running candidate's, measured over as many
        // steady frames as a probe's: until then no rasteriser is probed.
        for _ in 1..PROBE_FRAMES {
            governor.observe(DIFFERENTIAL, Motion::Still, 0.5, true, None);
            assert_eq!(governor.decide(Motion::Still, false), Action::Stay);
        }
        governor.observe(DIFFERENTIAL, Motion::Still, 0.5, true, None);
        // Then the most promising within reach: dir (123× differential's 0.5 ms: 62 ms,
        // within 1.5 budgets).
        let dir_ms = governor.estimated_cost(DIR, Motion::Still).unwrap();
        assert!(dir_ms > 50.0 && dir_ms <= 75.0, "{dir_ms}");
        assert_eq!(governor.decide(Motion::Still, false), Action::Probe(DIR));
    }

    /// A rasteriser that ties the running choice on error and that the ratios put clearly
    /// cheaper would win the tie on cost, so it is measured, and then chosen: desk_box's
    /// features, `dlpv` (2.3× `differential` while still) against `dir` at 64 VPLs (19 ms).
    #[test]
    fn an_unmeasured_rasteriser_that_would_win_a_tie_on_cost_is_probed() {
        const DVCT: usize = 3;
        let desk_box = features(3.79, 0.75, 0.86);
        let mut governor = fresh(desk_box, 33.0);
        for c in [DVCT, DIR, PT] {
            governor.mark_unavailable(c);
        }
        measure(&mut governor, DIFFERENTIAL, 5.0);
        measure(&mut governor, DIR64, 19.0);
        governor.switched(DIR64);
        let (dlpv, dir64) = (
            governor.predicted_error(DLPV, Motion::Still),
            governor.predicted_error(DIR64, Motion::Still),
        );
        assert!(
            dlpv <= dir64 * (1.0 + TIE) + SLACK && dir64 <= dlpv * (1.0 + TIE) + SLACK,
            "{dlpv} against {dir64}"
        );
        assert_eq!(governor.decide(Motion::Still, false), Action::Probe(DLPV));
        governor.switched(DLPV);
        for frame in 1..=WARM_UP_FRAMES + PROBE_FRAMES {
            governor.observe(DLPV, Motion::Still, 6.5, frame > WARM_UP_FRAMES, None);
            assert_eq!(governor.decide(Motion::Still, false), Action::Stay);
        }
        assert_eq!(governor.current(), DLPV);
        assert!(
            governor.reason().contains("cheapest of 2"),
            "{}",
            governor.reason()
        );
    }

    /// desk_box's features at a 1000 ms budget over the 4 s a scene is judged at, with
    /// lavapipe's frames at 160 × 120 and `pt` tracing 15 samples per pixel a frame of noise
    /// `pt_noise` (at its 60 samples by the horizon, `pt_noise` / √60), `unavailable` left
    /// out: the candidates probed, in order, the one chosen, and when it settled (ms).
    fn desk_box_at_1000_ms(unavailable: &[usize], pt_noise: f64) -> (Vec<usize>, usize, f64) {
        let mut governor = fresh(features(3.79, 0.75, 0.86), 1000.0);
        governor.set_settings(Settings {
            horizon_ms: 4000.0,
            ..governor.settings()
        });
        for &c in unavailable {
            governor.mark_unavailable(c);
        }
        let frame_ms = [5.0, 5.0, 6.0, 90.0, 18.0, 55.0, 1000.0];
        let (mut elapsed, mut samples) = (0.0, 0.0);
        let (mut frames_on, mut ms_on) = (0, 0.0);
        let mut probed = Vec::new();
        while elapsed < 4000.0 {
            let current = governor.current();
            let ms = frame_ms[current];
            let steady = frames_on > 0 && (ms_on >= WARM_UP_MS || frames_on >= WARM_UP_FRAMES);
            let pt = (current == PT).then(|| {
                samples += 15.0;
                PtFrame {
                    path_samples: samples,
                    samples_added: 15.0,
                    estimated_error: Some(pt_noise / f64::sqrt(samples)),
                }
            });
            governor.observe(current, Motion::Still, ms, steady, pt);
            (frames_on, ms_on) = (frames_on + 1, ms_on + ms);
            elapsed += ms.max(SENSOR_PERIOD_MS);
            if let Action::Switch(c) | Action::Probe(c) = governor.decide(Motion::Still, false) {
                if governor.probing() == Some(c) {
                    probed.push(c);
                }
                governor.switched(c);
                (frames_on, ms_on) = (0, 0.0);
            }
            if governor.settled() && governor.current() != PT && probed.contains(&PT) {
                break;
            }
        }
        (probed, governor.current(), elapsed)
    }

    /// At a 1000 ms budget on desk_box `pt` is probed first (its prior wins) and measured in
    /// one steady frame that traced its 16 samples; `dir`, which its shares put clearly ahead
    /// of `pt`'s 0.245 and of every other rasteriser there (0.130 against `dlpv`'s 0.164; the
    /// bench measures 0.126 and 0.157), is probed next and chosen.
    #[test]
    fn on_desk_box_with_time_to_spare_dir_is_chosen() {
        let (probed, current, elapsed) = desk_box_at_1000_ms(&[], 1.9);
        assert_eq!(probed, [PT, DIR]);
        assert_eq!(current, DIR);
        assert!(elapsed < 3000.0, "settled after {elapsed} ms");
    }

    /// Without `dir`, and with `pt` (noise 1.24: 0.16 by the horizon) tying the rasterisers
    /// left (`dlpv` 0.164, `dvct` 0.167) on error at over ten times their cost: they are
    /// estimated from its cost per sample (with none measured there was no cost to find them
    /// cheaper by, and `pt`'s 0.26 once stood against `dlpv`'s 0.22), the cheapest that ties
    /// is probed, and chosen, well inside the 4 s the scene is judged at.
    #[test]
    fn after_pt_alone_is_measured_the_rasterisers_that_tie_it_are() {
        let (probed, current, elapsed) = desk_box_at_1000_ms(&[DIR, DIR64], 1.24);
        // pt, then the cheapest that ties, which rules out the dearer.
        assert_eq!(probed, [PT, DLPV]);
        assert_eq!(current, DLPV);
        assert!(elapsed < 3000.0, "settled after {elapsed} ms");
    }

    /// Where the measured rasterisers cost alike (a GPU, whose frames are mostly their fixed
    /// part), the cost ratios' spread is not believed: `dir`, over a hundred times
    /// `differential` by the ratios, is estimated at the measured frames' cost and probed at a
    /// budget it fits.
    #[test]
    fn rasterisers_measured_alike_bring_the_others_estimates_down_to_them() {
        let mut governor = fresh(features(2.0, 6.0, 4.0), 5.0);
        governor.mark_unavailable(PT);
        measure(&mut governor, DIFFERENTIAL, 3.0);
        // One rasteriser measured: the ratios in full, dir far over the budget.
        let estimate = |g: &Governor| g.estimated_cost(DIR, Motion::Still).unwrap();
        let dir_ratio = governor.ratio(DIR, DIFFERENTIAL, Motion::Still);
        assert!(dir_ratio > 10.0, "{dir_ratio}");
        assert!(
            (estimate(&governor) - 3.0 * dir_ratio).abs() < 1.0,
            "{}",
            estimate(&governor)
        );
        // dlpv, over twice differential by the ratios and within reach, is probed and
        // measured cheaper.
        assert_eq!(governor.decide(Motion::Still, false), Action::Probe(DLPV));
        governor.switched(DLPV);
        let action = next_after_probe(&mut governor, DLPV, 2.5);
        assert_eq!(estimate(&governor), 3.0);
        assert_eq!(action, Action::Probe(DIR), "{}", governor.reason());
        // Measured as the ratios have it (lavapipe), the ratios stand.
        let mut governor = measured(features(2.0, 6.0, 4.0), 33.0);
        governor.costs[DIR][Motion::Still.index()].0.clear();
        assert!(
            (estimate(&governor) - 5.0 * dir_ratio).abs() < 1.0,
            "{}",
            estimate(&governor)
        );
    }

    /// A winner priced out by the ratios alone, with no second rasteriser to check them by:
    /// the one the ratios put dearest within reach is measured first (`ibl` here, no better
    /// than `differential`), and measured alike, `dir` is then within reach and probed.
    #[test]
    fn unchecked_ratios_are_checked_before_they_keep_a_winner_out() {
        // Under an environment map, where `ibl`'s ratio is its own.
        let environment = SceneFeatures {
            environment: true,
            ..features(2.0, 6.0, 4.0)
        };
        let mut governor = fresh(environment, 5.0);
        for c in [DLPV, PT] {
            governor.mark_unavailable(c);
        }
        measure(&mut governor, DIFFERENTIAL, 4.6);
        let action = governor.decide(Motion::Still, false);
        assert_eq!(action, Action::Probe(IBL), "{}", governor.reason());
        governor.switched(IBL);
        let action = next_after_probe(&mut governor, IBL, 4.6);
        assert_eq!(action, Action::Probe(DIR), "{}", governor.reason());
    }

    /// Without an environment map `ibl` renders as `differential`: it costs the same, so it
    /// checks no ratio and is not measured as a check.
    #[test]
    fn ibl_without_an_environment_map_costs_what_differential_does() {
        let mut governor = fresh(features(2.0, 6.0, 4.0), 5.0);
        for c in [DLPV, PT] {
            governor.mark_unavailable(c);
        }
        measure(&mut governor, DIFFERENTIAL, 4.6);
        assert_eq!(governor.estimated_cost(IBL, Motion::Still), Some(4.6));
        let action = governor.decide(Motion::Still, false);
        assert_ne!(action, Action::Probe(IBL), "{}", governor.reason());
    }

    /// window_env at 10 ms: `differential` measured at 13 ms, `dlpv` alike (so the ratios'
    /// spread is not believed and `ibl` is estimated at 13 ms, within reach of a probe), `pt`
    /// fitting at a third of a sample a frame. `ibl` is predicted clearly more accurate than
    /// `pt`, but cannot fit where the cheapest rasteriser does not: it is not probed.
    #[test]
    fn no_rasteriser_is_probed_where_the_cheapest_does_not_fit() {
        let window_env = SceneFeatures {
            environment: true,
            ..features(32.4, 2.4, 0.0)
        };
        let mut governor = fresh(window_env, 10.0);
        measure(&mut governor, DIFFERENTIAL, 13.0);
        measure(&mut governor, DLPV, 13.0);
        for samples in 1..=60 {
            let samples = f64::from(samples) / 3.0;
            let pt = PtFrame {
                path_samples: samples,
                samples_added: 1.0 / 3.0,
                estimated_error: Some(0.67 / samples.sqrt()),
            };
            governor.observe(PT, Motion::Still, 10.0, true, Some(pt));
        }
        governor.switched(PT);
        let (ibl, pt) = (
            governor.predicted_error(IBL, Motion::Still),
            governor.predicted_error(PT, Motion::Still),
        );
        assert!(ibl * (1.0 + TIE) + SLACK < pt, "{ibl} against {pt}");
        assert_eq!(governor.estimated_cost(IBL, Motion::Still), Some(13.0));
        for _ in 0..MIN_DWELL {
            governor.observe(PT, Motion::Still, 10.0, true, None);
            let action = governor.decide(Motion::Still, false);
            assert_eq!(action, Action::Stay, "{}", governor.reason());
        }
    }

    /// A governor at 33 ms on a bleeding scene with only `differential` and `kept` available:
    /// `differential` measured at 5 ms, and `kept` (which would win) being probed.
    fn probing_beside_differential(kept: usize) -> Governor {
        let mut governor = fresh(features(2.0, 6.0, 4.0), 33.0);
        for candidate in (0..candidates().len()).filter(|&c| c != DIFFERENTIAL && c != kept) {
            governor.mark_unavailable(candidate);
        }
        // Cheap enough that the ratios put `kept` within reach of the budget.
        measure(&mut governor, DIFFERENTIAL, 1.0);
        assert_eq!(governor.decide(Motion::Still, false), Action::Probe(kept));
        governor.switched(kept);
        governor
    }

    #[test]
    fn pt_fits_a_budget_under_its_sample_by_tracing_a_share_of_one() {
        let mut governor = probing_beside_differential(PT);
        // A sample per pixel costs 40 ms, over the budget: a frame traces 33/40 of one, and
        // the probe measures pt's noise (1.2 at a sample) until it holds 16.
        let share = 33.0 / 40.0;
        let mut samples = 0.0;
        let mut frames = 0;
        while governor.probing().is_some() {
            frames += 1;
            samples += share;
            let pt = PtFrame {
                path_samples: samples,
                samples_added: share,
                estimated_error: Some(1.2 / f64::sqrt(samples)),
            };
            governor.observe(PT, Motion::Still, 33.0, frames > WARM_UP_FRAMES, Some(pt));
            assert_eq!(governor.decide(Motion::Still, false), Action::Stay);
            assert!(frames < 40, "{}", governor.reason());
        }
        assert!(samples >= PT_PROBE_SAMPLES, "{samples}");
        // It fits, and is kept: 33/40 of a sample a frame for the horizon's 60 frames.
        assert_eq!(governor.cost(PT, Motion::Still), Some(33.0));
        assert_eq!(governor.current(), PT, "{}", governor.reason());
        let predicted = governor.predicted_error(PT, Motion::Still);
        let expected = 1.2 / (share * 2000.0 / 33.0).sqrt();
        assert!(
            (predicted - expected).abs() < 1e-3,
            "{predicted} vs {expected}"
        );
    }

    #[test]
    fn a_candidate_priced_out_in_a_slow_spell_is_probed_again_later() {
        let mut governor = probing_beside_differential(DIR64);
        // Probed in a slow spell (45 ms): over the budget, so back to differential.
        let (action, _) = probe(&mut governor, DIR64, 45.0);
        assert_eq!(action, Action::Switch(DIFFERENTIAL));
        governor.switched(DIFFERENTIAL);
        // Not probed again within REPROBE_FRAMES ...
        let switches = run(&mut governor, Motion::Still, REPROBE_FRAMES as u32 - 10);
        assert!(switches.is_empty(), "{switches:?}: {}", governor.reason());
        // ... but after them; the spell has passed (20 ms), so it is kept.
        let mut probed = false;
        for _ in 0..40 {
            let current = governor.current();
            let ms = if current == DIR64 { 20.0 } else { 1.0 };
            governor.observe(current, Motion::Still, ms, true, None);
            if let Action::Switch(c) | Action::Probe(c) = governor.decide(Motion::Still, false) {
                probed |= governor
                    .reason()
                    .contains("over the budget when last measured");
                governor.switched(c);
            }
        }
        assert!(probed);
        assert_eq!(governor.current(), DIR64, "{}", governor.reason());
        assert_eq!(governor.cost(DIR64, Motion::Still), Some(20.0));
    }

    #[test]
    fn it_does_not_flap_when_the_features_wobble_across_a_choice() {
        // A little bleeding ties dlpv with differential (the cheaper is chosen); more makes
        // dlpv the choice. The features alternate between the two every frame.
        let (little, more) = (features(1.0, 0.02, 0.0), features(1.0, 0.3, 0.0));
        let mut governor = measured(little, 10.0);
        assert_eq!(governor.choose(Motion::Still).0, DIFFERENTIAL);
        governor.set_features(more);
        assert_eq!(governor.choose(Motion::Still).0, DLPV);
        let mut switches = 0;
        for frame in 0..200 {
            governor.set_features(if frame % 2 == 0 { little } else { more });
            switches += run(&mut governor, Motion::Still, 1).len();
        }
        assert!(switches <= 1, "{switches} switches");
    }

    #[test]
    fn a_better_candidate_waits_for_the_dwell_and_over_budget_does_not() {
        let mut governor = measured(features(2.0, 6.0, 4.0), 33.0);
        governor.switched(DIFFERENTIAL);
        // dir64 is far better, but a switch happened just now.
        for _ in 1..MIN_DWELL {
            governor.observe(DIFFERENTIAL, Motion::Still, 5.0, true, None);
            assert_eq!(governor.decide(Motion::Still, false), Action::Stay);
        }
        governor.observe(DIFFERENTIAL, Motion::Still, 5.0, true, None);
        assert_eq!(governor.decide(Motion::Still, false), Action::Switch(DIR64));
        governor.switched(DIR64);
        // The budget drops under dir64's cost: it leaves after OVER_BUDGET_FRAMES frames over,
        // without waiting for the dwell.
        governor.set_settings(Settings {
            budget_ms: 10.0,
            ..governor.settings()
        });
        let mut frames = 0;
        loop {
            frames += 1;
            governor.observe(DIR64, Motion::Still, 20.0, true, None);
            if let Action::Switch(c) = governor.decide(Motion::Still, false) {
                // pt fits any budget its least step does (its noise grows as it must).
                assert!([DIFFERENTIAL, IBL, DLPV, PT].contains(&c));
                break;
            }
            assert!(
                frames < 10,
                "still on dir64 after {frames} frames over budget"
            );
        }
        assert!(frames <= OVER_BUDGET_FRAMES, "{frames}");
    }
}
