//! The GPU depth reconstruction against its CPU oracle (`relight-recon`) on the same inputs:
//! simulated Kinect frames at 160 × 120 (noise, quantisation, holes, projector shadows) and
//! hand-made frames of invalid values.
//!
//! # Tolerances
//!
//! Both sides evaluate the same f32 arithmetic in the same order (see `recon_gpu`'s module
//! docs); they can differ only where WGSL leaves rounding to the implementation: FMA
//! contraction of `a * b + c`, division (2.5 ULP in Vulkan) and square root. Lavapipe does
//! neither, and there every output is bit-identical to the oracle's; a GPU that fuses or
//! approximates rounds differently, by as much as a second correct f32 evaluation would:
//!
//! - Filtered depth: the filter works in disparity q = 1/z, so its rounding error in z scales
//!   as z² Δq. Against an f64 evaluation of the same algorithm, the f32 oracle's error on the
//!   simulated scenes (desk_box, spot_bleed, touching_wall; 160 × 120 and 320 × 240, r = 4) is
//!   at most 2.2 × 10⁻⁶ · z² m (99.9 % of pixels below 1.5 × 10⁻⁶ · z²; it grows with the
//!   radius: 4.6 × 10⁻⁶ at r = 16). Two f32 evaluations each that close to the exact value are
//!   within twice that of each other; with a factor 2 of margin the tolerance is
//!   [`DEPTH_TOLERANCE_PER_M`] · z² (0.04 mm at 2 m, 0.2 mm at 4.5 m: a thirtieth of the
//!   sensor's σ). The deviation guard is a threshold on the filtered value: where the oracle's
//!   |z − raw| lies within the tolerance of 3 σ, the two may keep different values; such a
//!   pixel must keep the raw depth on one side and sit on the threshold on the other.
//! - Normals, on the same depth: points and tangents are single correctly rounded products and
//!   differences, identical on every GPU; the cross product and the normalisation may each be
//!   off by a few ULP, which turns the normal by ~4 ULP / sin(angle between the tangents) rad.
//!   [`NORMAL_TOLERANCE_DEG`] = 0.01° (1.7 × 10⁻⁴ rad) allows tangents down to 0.3° apart.
//! - Merge, on the same filtered depth: the oracle projects into the previous camera in f64,
//!   the GPU in f32, so the landing pixel differs by a few ULP of the pixel coordinate
//!   (~10⁻⁴ px), the bilinear history read by that times the depth gradient, and the running
//!   mean carries it over frames. Measured here over an orbit: ≤ 2 µm (≤ 5.2 × 10⁻⁷ · z²) after
//!   six frames; the depth tolerance above bounds it. The agreement test and the landing
//!   inside the image are thresholds: a pixel on one may decide differently; at most
//!   [`MAX_FLIPPED_SHARE`] of the pixels may.
//!
//! Run with `--nocapture` to see the measured differences.

use std::path::Path;
use std::sync::Arc;

use std::time::Instant;

use relight_core::camera::Pinhole;
use relight_core::scene::Scene;
use relight_core::{Image, PixelFormat, Pose, StreamMessage};
use relight_engines::gpu::GpuContext;
use relight_engines::recon_gpu::{DepthFrame, DepthPass, DepthPassSettings, ReconGpuError};
use relight_recon::depth::{
    DepthError, DepthMap, DepthRange, GuidedFilterSettings, guided_filter, is_valid_depth,
};
use relight_recon::normals::{NormalMap, normals, positions};
use relight_recon::temporal::{ResetReason, TemporalMerge};
use relight_sim::rig::{CameraPath, SimRig, SimSettings};
use relight_sim::trajectory::Trajectory;

/// Filtered depth may differ by this times z² (metres); see the module docs.
const DEPTH_TOLERANCE_PER_M: f32 = 1e-5;
/// Normals computed from the same depth may differ by this.
const NORMAL_TOLERANCE_DEG: f32 = 0.01;
/// Share of pixels whose merge decision may differ (threshold cases).
const MAX_FLIPPED_SHARE: f32 = 0.005;

fn depth_tolerance(z: f32) -> f32 {
    DEPTH_TOLERANCE_PER_M * z * z
}

fn gpu() -> Arc<GpuContext> {
    Arc::new(GpuContext::new().expect("a GPU adapter (lavapipe: mesa-vulkan-drivers)"))
}

fn load_scene(name: &str) -> Scene {
    Scene::load(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../tests/scenes")
            .join(name),
    )
    .unwrap()
}

/// The rig of the oracle's tests: 160 × 120, 4 spp colour, no probe or marker board.
fn rig(scene: &Scene, trajectory: Option<Trajectory>, frames: u32) -> SimRig {
    let settings = SimSettings {
        width: 160,
        height: 120,
        frames,
        color_spp: 4,
        trajectory,
        probe: None,
        board: None,
        ..SimSettings::placed_in(scene)
    };
    SimRig::new(scene, settings).unwrap().metered()
}

/// Depth (decoded as the daemon decodes it), colour and pose of frame `i`.
fn sim_frame(rig: &SimRig, i: u32) -> (DepthMap, Image, Pose) {
    let frame = rig.frame(i);
    let mut depth = None;
    let mut color = None;
    for message in frame.messages {
        match message {
            StreamMessage::Depth(f) => depth = Some(f.payload.clone()),
            StreamMessage::Color(f) => color = Some(f.payload.clone()),
            _ => {}
        }
    }
    let depth = DepthMap::from_image(&depth.unwrap(), DepthRange::default()).unwrap();
    (depth, color.unwrap(), rig.world_from_camera(i))
}

fn filter_only(camera: &Pinhole) -> DepthPassSettings {
    DepthPassSettings {
        temporal: None,
        ..DepthPassSettings::kinect_v1(camera.fx as f32)
    }
}

/// The spot_bleed scene with its box made real: a depth edge with a colour edge, projector
/// shadows beside it.
fn spot_bleed_with_real_box() -> Scene {
    let mut scene = load_scene("spot_bleed");
    scene.meshes.iter_mut().for_each(|m| m.is_virtual = false);
    scene
}

/// How far two depth maps are apart.
#[derive(Debug, Default)]
struct DepthDiff {
    /// Largest |Δz| over pixels valid in both, metres, and that over the tolerance scale.
    max_m: f32,
    max_scaled: f32,
    /// Pixels valid in one map only.
    validity: usize,
}

fn depth_diff(gpu: &DepthMap, cpu: &DepthMap, scale: impl Fn(f32) -> f32) -> DepthDiff {
    let mut diff = DepthDiff::default();
    for (g, c) in gpu.metres.iter().zip(&cpu.metres) {
        assert!(g.is_finite(), "GPU depth {g}");
        match (is_valid_depth(*g), is_valid_depth(*c)) {
            (true, true) => {
                let d = (g - c).abs();
                diff.max_m = diff.max_m.max(d);
                diff.max_scaled = diff.max_scaled.max(d / scale(*c));
            }
            (false, false) => {}
            _ => diff.validity += 1,
        }
    }
    diff
}

/// Largest angle (degrees) between the normals of two maps, and how many pixels have a normal
/// in one only.
fn normal_diff(gpu: &NormalMap, cpu: &NormalMap) -> (f32, usize) {
    let mut max_deg = 0.0f32;
    let mut presence = 0;
    for (g, c) in gpu.normals_in_camera.iter().zip(&cpu.normals_in_camera) {
        match (g, c) {
            (Some(g), Some(c)) => {
                assert!((g.length() - 1.0).abs() < 1e-5, "GPU normal {g}");
                let angle = g.dot(*c).clamp(-1.0, 1.0).acos().to_degrees();
                // acos near 1 loses half the digits: use the chord for small angles.
                let chord = (*g - *c).length().to_degrees();
                max_deg = max_deg.max(angle.min(chord));
            }
            (None, None) => {}
            _ => presence += 1,
        }
    }
    (max_deg, presence)
}

fn cpu_normals(depth: &DepthMap, camera: &Pinhole, settings: &DepthPassSettings) -> NormalMap {
    normals(&positions(depth, camera).unwrap(), &settings.normals)
}

/// The oracle's merge on the GPU's filtered depth (from a filter-only pass over the same
/// inputs), beside the GPU's merge: the comparison isolates the merge.
struct MergeComparison {
    camera: Pinhole,
    filter: DepthPass,
    merge: DepthPass,
    oracle: TemporalMerge,
    settings: DepthPassSettings,
}

impl MergeComparison {
    fn new(ctx: &Arc<GpuContext>, camera: Pinhole) -> Self {
        let settings = DepthPassSettings::kinect_v1(camera.fx as f32);
        Self {
            camera,
            filter: DepthPass::new(ctx.clone()),
            merge: DepthPass::new(ctx.clone()),
            oracle: TemporalMerge::new(settings.temporal.unwrap()),
            settings,
        }
    }

    /// One frame: (GPU frame, GPU filtered depth, oracle's merged depth).
    fn frame(
        &mut self,
        raw: &DepthMap,
        color: &Image,
        pose: &Pose,
    ) -> (DepthFrame, DepthMap, DepthMap) {
        let filtered = self
            .filter
            .run(raw, color, &self.camera, pose, &filter_only(&self.camera))
            .unwrap()
            .depth;
        let gpu = self
            .merge
            .run(raw, color, &self.camera, pose, &self.settings)
            .unwrap();
        let cpu = self.oracle.merge(&filtered, &self.camera, pose).unwrap();
        (gpu, filtered, cpu)
    }

    /// Checks one frame against the oracle; returns the largest |Δz| (m).
    fn check(&mut self, raw: &DepthMap, color: &Image, pose: &Pose, label: &str) -> DepthFrame {
        let (gpu, _, cpu) = self.frame(raw, color, pose);
        let report = gpu.merge.expect("a merge report");
        let oracle = *self.oracle.report();
        let diff = depth_diff(&gpu.depth, &cpu, |z| z * z);
        let beyond = gpu
            .depth
            .metres
            .iter()
            .zip(&cpu.metres)
            .filter(|(g, c)| (*g - *c).abs() > depth_tolerance(**c))
            .count();
        println!(
            "{label}: merged depth max |Δ| {:.4} mm ({:.2e} · z²), {beyond} px beyond the \
             tolerance; GPU {report:?}, oracle {oracle:?}",
            diff.max_m * 1e3,
            diff.max_scaled,
        );
        let pixels = raw.pixel_count() as f32;
        assert_eq!(diff.validity, 0, "{label}: the merge keeps validity");
        assert!(
            beyond as f32 <= MAX_FLIPPED_SHARE * pixels,
            "{label}: {beyond} px"
        );
        assert_eq!(
            std::mem::discriminant(&report.reset),
            std::mem::discriminant(&oracle.reset),
            "{label}: {report:?} vs {oracle:?}"
        );
        let flipped =
            report.merged.abs_diff(oracle.merged) + report.rejected.abs_diff(oracle.rejected);
        assert!(
            flipped as f32 <= MAX_FLIPPED_SHARE * pixels,
            "{label}: {report:?} vs {oracle:?}"
        );
        assert_eq!(
            report.merged + report.rejected + report.fresh,
            oracle.merged + oracle.rejected + oracle.fresh
        );
        let (angle, presence) = normal_diff(
            &gpu.normals,
            &cpu_normals(&gpu.depth, &self.camera, &self.settings),
        );
        assert_eq!(presence, 0, "{label}");
        assert!(angle <= NORMAL_TOLERANCE_DEG, "{label}: {angle}°");
        gpu
    }
}

#[test]
fn guided_filter_and_normals_match_the_cpu_oracle() {
    let ctx = gpu();
    for (name, scene) in [
        ("desk_box", load_scene("desk_box")),
        ("spot_bleed, real box", spot_bleed_with_real_box()),
    ] {
        let rig = rig(&scene, None, 1);
        let camera = *rig.camera();
        let (raw, color, pose) = sim_frame(&rig, 0);
        let grey = {
            let mut grey = Image::new(color.width(), color.height(), PixelFormat::Mono8);
            let rgb = color.as_u8().unwrap();
            for (g, c) in grey
                .as_u8_mut()
                .unwrap()
                .iter_mut()
                .zip(rgb.chunks_exact(3))
            {
                *g = ((u32::from(c[0]) + u32::from(c[1]) + u32::from(c[2])) / 3) as u8;
            }
            grey
        };
        let settings = filter_only(&camera);
        let mut pass = DepthPass::new(ctx.clone());
        for (guide_name, guide) in [("RGB", &color), ("grey", &grey)] {
            let label = format!("{name}, {guide_name} guide");
            let gpu = pass.run(&raw, guide, &camera, &pose, &settings).unwrap();
            let cpu = guided_filter(&raw, guide, &settings.filter).unwrap();
            let changed = cpu
                .metres
                .iter()
                .zip(&raw.metres)
                .filter(|(c, r)| c != r)
                .count();
            let diff = depth_diff(&gpu.depth, &cpu, |z| z * z);
            assert_eq!(diff.validity, 0, "{label}: the filter keeps validity");
            // Pixels beyond the tolerance must be deviation-guard decisions on the threshold.
            let mut guard_flips = 0;
            for ((g, c), r) in gpu.depth.metres.iter().zip(&cpu.metres).zip(&raw.metres) {
                if (g - c).abs() <= depth_tolerance(*c) {
                    continue;
                }
                let limit =
                    settings.filter.max_deviation_sigmas * settings.filter.noise.sigma_m(*r);
                let filtered = if g == r { c } else { g };
                assert!(
                    (g == r || c == r)
                        && ((filtered - r).abs() - limit).abs() <= depth_tolerance(*r),
                    "{label}: GPU {g} m, oracle {c} m, raw {r} m"
                );
                guard_flips += 1;
            }
            assert!(guard_flips as f32 <= MAX_FLIPPED_SHARE * raw.pixel_count() as f32);
            let (angle, presence) =
                normal_diff(&gpu.normals, &cpu_normals(&gpu.depth, &camera, &settings));
            let (end_to_end, end_to_end_presence) =
                normal_diff(&gpu.normals, &cpu_normals(&cpu, &camera, &settings));
            println!(
                "{label}: {changed} of {} px filtered; depth max |Δ| {:.4} mm ({:.2e} · z², \
                 tolerance {DEPTH_TOLERANCE_PER_M:.0e}), {guard_flips} guard flips; normals on \
                 the same depth max {angle:.5}°, end to end {end_to_end:.5}° \
                 ({end_to_end_presence} px differ in having one)",
                raw.pixel_count(),
                diff.max_m * 1e3,
                diff.max_scaled,
            );
            assert!(
                changed > raw.pixel_count() / 2,
                "{label}: the filter did something"
            );
            assert!(diff.max_scaled <= DEPTH_TOLERANCE_PER_M || guard_flips > 0);
            assert_eq!(presence, 0, "{label}: normals exist where the oracle's do");
            assert!(angle <= NORMAL_TOLERANCE_DEG, "{label}: {angle}°");
            assert!(gpu.merge.is_none());
            for n in gpu.normals.normals_in_camera.iter().flatten() {
                assert!(n.is_finite() && (n.length() - 1.0).abs() < 1e-5);
            }
        }
    }
}

/// Knecht et al. Sec. 4.2 on an orbiting camera, frame after frame, with the oracle's resets:
/// a pose jump (45 frames skipped: 0.9 m, 26°) restarts from the current frame, the next frame
/// merges again, and a stale pose (the camera moved, its pose did not) is caught by the
/// agreement test.
#[test]
fn temporal_merge_matches_the_cpu_oracle_and_resets_like_it() {
    let ctx = gpu();
    let scene = load_scene("desk_box");
    let rig = rig(&scene, Some(CameraPath::Orbit.trajectory(&scene)), 60);
    let camera = *rig.camera();
    let mut cmp = MergeComparison::new(&ctx, camera);
    for i in [0, 1, 2, 3, 4, 5] {
        let (raw, color, pose) = sim_frame(&rig, i);
        let frame = cmp.check(&raw, &color, &pose, &format!("orbit frame {i}"));
        let report = frame.merge.unwrap();
        assert_eq!(report.reset.is_some(), i == 0, "{report:?}");
        if i > 0 {
            assert!(report.merged > 50 * report.rejected, "{report:?}");
        }
    }

    let (raw, color, pose) = sim_frame(&rig, 48);
    let (jumped, filtered, _) = cmp.frame(&raw, &color, &pose);
    let report = jumped.merge.unwrap();
    assert!(
        matches!(report.reset, Some(ResetReason::PoseJump { .. })),
        "{report:?}"
    );
    assert!(matches!(
        cmp.oracle.report().reset,
        Some(ResetReason::PoseJump { .. })
    ));
    assert_eq!(
        jumped.depth, filtered,
        "after the jump the output is the current frame's filtered depth, unblended"
    );
    let (raw, color, pose) = sim_frame(&rig, 49);
    let report = cmp
        .check(&raw, &color, &pose, "after the jump")
        .merge
        .unwrap();
    assert_eq!(report.reset, None);

    // Tracking lost: the camera keeps orbiting, its pose stays at frame 0's.
    let mut stale = MergeComparison::new(&ctx, camera);
    let stale_pose = rig.world_from_camera(0);
    let mut last = None;
    for i in [0, 1, 2, 48] {
        let (raw, color, _) = sim_frame(&rig, i);
        last = Some(stale.frame(&raw, &color, &stale_pose));
    }
    let (gpu, filtered, cpu) = last.unwrap();
    let report = gpu.merge.unwrap();
    println!(
        "stale pose: GPU {report:?}, oracle {:?}",
        stale.oracle.report()
    );
    let (
        Some(ResetReason::Disagreement { agreement }),
        Some(ResetReason::Disagreement { agreement: oracle }),
    ) = (report.reset, stale.oracle.report().reset)
    else {
        panic!(
            "expected disagreement resets: {report:?}, {:?}",
            stale.oracle.report()
        );
    };
    assert!((agreement - oracle).abs() <= MAX_FLIPPED_SHARE);
    assert_eq!(gpu.depth, filtered);
    assert_eq!(cpu, filtered);
}

const W: u32 = 32;
const H: u32 = 24;

fn small_camera(width: u32, height: u32) -> Pinhole {
    Pinhole {
        width,
        height,
        fx: 30.0,
        fy: 30.0,
        cx: f64::from(width - 1) / 2.0,
        cy: f64::from(height - 1) / 2.0,
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    }
}

/// A colour image with a vertical edge at a third of the width.
fn edge_guide(width: u32, height: u32) -> Image {
    let mut image = Image::new(width, height, PixelFormat::Rgb8);
    for (i, px) in image.as_u8_mut().unwrap().chunks_exact_mut(3).enumerate() {
        let x = i as u32 % width;
        px.copy_from_slice(if x < width / 3 {
            &[200, 40, 40]
        } else {
            &[60, 120, 200]
        });
    }
    image
}

#[test]
fn invalid_depth_never_becomes_geometry() {
    let ctx = gpu();
    let camera = small_camera(W, H);
    let guide = edge_guide(W, H);
    let settings = DepthPassSettings::kinect_v1(30.0);
    let n = (W * H) as usize;
    let invalid = [0.0, f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1.0, -0.0];
    let mut pass = DepthPass::new(ctx.clone());
    // All invalid, twice (the second frame merges with an empty history), every kind of value.
    for frame in 0..2 {
        let depth = DepthMap {
            width: W,
            height: H,
            metres: (0..n)
                .map(|i| invalid[(i + frame) % invalid.len()])
                .collect(),
        };
        let out = pass
            .run(&depth, &guide, &camera, &Pose::IDENTITY, &settings)
            .unwrap();
        assert!(
            out.depth.metres.iter().all(|z| *z == 0.0),
            "{:?}",
            out.depth.metres
        );
        assert!(out.normals.normals_in_camera.iter().all(Option::is_none));
        let report = out.merge.unwrap();
        assert_eq!((report.merged, report.rejected, report.fresh), (0, 0, 0));
    }
    // A slanted wall with holes of every kind: geometry exactly where the input has depth.
    let slanted = |i: usize| 1.5 + 0.02 * (i % W as usize) as f32 + 0.01 * (i / W as usize) as f32;
    pass.reset();
    let mut merge = TemporalMerge::new(settings.temporal.unwrap());
    for frame in 0..3 {
        let metres: Vec<f32> = (0..n)
            .map(|i| {
                if (i * 7 + frame).is_multiple_of(5) {
                    invalid[i % invalid.len()]
                } else {
                    slanted(i)
                }
            })
            .collect();
        let depth = DepthMap {
            width: W,
            height: H,
            metres,
        };
        let out = pass
            .run(&depth, &guide, &camera, &Pose::IDENTITY, &settings)
            .unwrap();
        let filtered = guided_filter(&depth, &guide, &settings.filter).unwrap();
        let cpu = merge.merge(&filtered, &camera, &Pose::IDENTITY).unwrap();
        for (i, (z, input)) in out.depth.metres.iter().zip(&depth.metres).enumerate() {
            assert!(z.is_finite(), "pixel {i}: {z}");
            assert_eq!(*z > 0.0, is_valid_depth(*input), "pixel {i}: {input} → {z}");
            assert!(out.normals.normals_in_camera[i].is_none() || *z > 0.0);
        }
        // (Values may differ from the oracle's at last frame's holes: see
        // `a_still_camera_differs_from_the_oracle_only_where_the_last_frame_had_holes`.)
        assert_eq!(depth_diff(&out.depth, &cpu, |z| z * z).validity, 0);
        let report = out.merge.unwrap();
        assert_eq!(report.reset.is_some(), frame == 0);
        assert_eq!(
            report.merged + report.rejected + report.fresh,
            depth.valid_count()
        );
    }
}

#[test]
fn a_resized_frame_reallocates_and_restarts() {
    let ctx = gpu();
    let settings = DepthPassSettings::kinect_v1(30.0);
    let mut pass = DepthPass::new(ctx.clone());
    for (width, height) in [(W, H), (W + 8, H + 6), (W + 8, H + 6), (W, H)] {
        let camera = small_camera(width, height);
        let guide = edge_guide(width, height);
        let depth = DepthMap {
            width,
            height,
            metres: (0..width * height)
                .map(|i| 2.0 + 0.01 * (i % width) as f32)
                .collect(),
        };
        let out = pass
            .run(&depth, &guide, &camera, &Pose::IDENTITY, &settings)
            .unwrap();
        let cpu = guided_filter(&depth, &guide, &settings.filter).unwrap();
        assert_eq!((out.depth.width, out.depth.height), (width, height));
        assert_eq!(
            out.normals.normals_in_camera.len(),
            (width * height) as usize
        );
        let diff = depth_diff(&out.depth, &cpu, |z| z * z);
        assert!(
            diff.max_scaled <= DEPTH_TOLERANCE_PER_M && diff.validity == 0,
            "{diff:?}"
        );
    }
}

#[test]
fn a_wall_that_moved_under_a_still_pose_is_a_disagreement() {
    let ctx = gpu();
    let camera = small_camera(W, H);
    let guide = edge_guide(W, H);
    let settings = DepthPassSettings::kinect_v1(30.0);
    let mut pass = DepthPass::new(ctx.clone());
    let mut oracle = TemporalMerge::new(settings.temporal.unwrap());
    for wall_m in [2.0, 2.0, 2.5] {
        let depth = DepthMap {
            width: W,
            height: H,
            metres: vec![wall_m; (W * H) as usize],
        };
        let out = pass
            .run(&depth, &guide, &camera, &Pose::IDENTITY, &settings)
            .unwrap();
        let filtered = guided_filter(&depth, &guide, &settings.filter).unwrap();
        let cpu = oracle.merge(&filtered, &camera, &Pose::IDENTITY).unwrap();
        assert_eq!(out.merge.unwrap(), *oracle.report());
        assert_eq!(out.depth, cpu);
    }
    assert_eq!(
        oracle.report().reset,
        Some(ResetReason::Disagreement { agreement: 0.0 })
    );
    pass.reset();
    let depth = DepthMap {
        width: W,
        height: H,
        metres: vec![2.5; (W * H) as usize],
    };
    let out = pass
        .run(&depth, &guide, &camera, &Pose::IDENTITY, &settings)
        .unwrap();
    assert_eq!(out.merge.unwrap().reset, Some(ResetReason::FirstFrame));
}

#[test]
fn bad_inputs_are_errors() {
    let ctx = gpu();
    let camera = small_camera(W, H);
    let guide = edge_guide(W, H);
    let depth = DepthMap::invalid(W, H);
    let settings = DepthPassSettings::kinect_v1(30.0);
    let mut pass = DepthPass::new(ctx);
    let pose = Pose::IDENTITY;
    let err = |r: Result<DepthFrame, ReconGpuError>| match r {
        Err(ReconGpuError::Depth(e)) => e,
        other => panic!("expected a depth error, got {other:?}"),
    };
    assert!(matches!(
        err(pass.run(&depth, &edge_guide(W + 1, H), &camera, &pose, &settings)),
        DepthError::SizeMismatch {
            what: "guide image",
            ..
        }
    ));
    assert!(matches!(
        err(pass.run(&depth, &guide, &small_camera(W, H + 1), &pose, &settings)),
        DepthError::SizeMismatch { what: "camera", .. }
    ));
    assert!(matches!(
        err(pass.run(
            &depth,
            &Image::new(W, H, PixelFormat::DepthF32M),
            &camera,
            &pose,
            &settings
        )),
        DepthError::BadGuide { .. }
    ));
    let short = DepthMap {
        width: W,
        height: H,
        metres: vec![1.0; 3],
    };
    assert!(matches!(
        err(pass.run(&short, &guide, &camera, &pose, &settings)),
        DepthError::BadLength { .. }
    ));
    let mut bad = settings;
    bad.filter.radius_px = 65;
    assert!(matches!(
        err(pass.run(&depth, &guide, &camera, &pose, &bad)),
        DepthError::Setting {
            setting: "radius_px",
            ..
        }
    ));
    let mut bad = settings;
    if let Some(t) = bad.temporal.as_mut() {
        t.max_weight = 0.5;
    }
    assert!(matches!(
        err(pass.run(&depth, &guide, &camera, &pose, &bad)),
        DepthError::Setting {
            setting: "temporal",
            ..
        }
    ));
    // And the pass still works afterwards.
    assert!(pass.run(&depth, &guide, &camera, &pose, &settings).is_ok());
}

/// Not a test of speed (benchmarks are `relightd bench`): prints the wall clock and the pass
/// timings of 640 × 480 frames, and the oracle's for comparison. Run with
/// `cargo test -p relight-engines --test recon_gpu -- --ignored --nocapture`.
#[test]
#[ignore = "timings only"]
fn vga_frame_timings() {
    let ctx = gpu();
    let (width, height) = (640, 480);
    let camera = Pinhole {
        fx: 570.0,
        fy: 570.0,
        ..small_camera(width, height)
    };
    let guide = edge_guide(width, height);
    let depth = DepthMap {
        width,
        height,
        metres: (0..width * height)
            .map(|i| {
                if i.is_multiple_of(13) {
                    0.0
                } else {
                    1.0 + 0.002 * (i % width) as f32
                }
            })
            .collect(),
    };
    let mut pass = DepthPass::new(ctx);
    let mut out = DepthFrame::default();
    for radius_px in [4, 16] {
        let settings = DepthPassSettings {
            filter: GuidedFilterSettings {
                radius_px,
                ..GuidedFilterSettings::kinect_v1(570.0)
            },
            ..DepthPassSettings::kinect_v1(570.0)
        };
        for frame in 0..3 {
            let started = Instant::now();
            pass.run_into(
                &depth,
                &guide,
                &camera,
                &Pose::IDENTITY,
                &settings,
                &mut out,
            )
            .unwrap();
            println!(
                "640 × 480, r = {radius_px}, frame {frame}: {:.1} ms; {:?}",
                started.elapsed().as_secs_f64() * 1e3,
                out.timings
            );
        }
        let started = Instant::now();
        let cpu = guided_filter(&depth, &guide, &settings.filter).unwrap();
        println!(
            "oracle guided filter alone, r = {radius_px}: {:.1} ms",
            started.elapsed().as_secs_f64() * 1e3
        );
        assert_eq!(out.depth.valid_count(), cpu.valid_count());
    }
}

/// A still camera whose holes move from frame to frame (the synthetic case; the simulator's
/// holes stay put): the warp is the identity, so each pixel lands on its own pixel centre up to
/// rounding. Where that pixel was a hole in the previous frame, the oracle's renormalised
/// bilinear read is discontinuous there: landing 10⁻⁷ px to one side gives that neighbour a tiny
/// weight, renormalised to the whole history value; landing exactly on the centre finds no
/// history. The oracle projects in f64 and lands beside the centre, the GPU in f32 and lands on
/// it, so those pixels (and only those) differ: merged with a neighbour's history in one, fresh
/// in the other.
#[test]
fn a_still_camera_differs_from_the_oracle_only_where_the_last_frame_had_holes() {
    let ctx = gpu();
    let camera = small_camera(W, H);
    let guide = edge_guide(W, H);
    let settings = DepthPassSettings::kinect_v1(30.0);
    let n = (W * H) as usize;
    let slanted = |i: usize| 1.5 + 0.02 * (i % W as usize) as f32 + 0.01 * (i / W as usize) as f32;
    let frame = |k: usize| DepthMap {
        width: W,
        height: H,
        metres: (0..n)
            .map(|i| {
                if (i * 7 + k).is_multiple_of(5) {
                    0.0
                } else {
                    slanted(i)
                }
            })
            .collect(),
    };
    let mut pass = DepthPass::new(ctx);
    let mut oracle = TemporalMerge::new(settings.temporal.unwrap());
    for k in 0..2 {
        let depth = frame(k);
        let gpu = pass
            .run(&depth, &guide, &camera, &Pose::IDENTITY, &settings)
            .unwrap();
        let filtered = guided_filter(&depth, &guide, &settings.filter).unwrap();
        let cpu = oracle.merge(&filtered, &camera, &Pose::IDENTITY).unwrap();
        assert_eq!(depth_diff(&gpu.depth, &cpu, |z| z * z).validity, 0);
        let beyond: Vec<usize> = (0..n)
            .filter(|&i| {
                (gpu.depth.metres[i] - cpu.metres[i]).abs() > depth_tolerance(cpu.metres[i])
            })
            .collect();
        println!(
            "still camera, frame {k}: {} px beyond the tolerance; GPU {:?}, oracle {:?}",
            beyond.len(),
            gpu.merge,
            oracle.report()
        );
        if k == 0 {
            assert!(beyond.is_empty());
            continue;
        }
        let previous = frame(k - 1);
        for &i in &beyond {
            assert_eq!(
                previous.metres[i], 0.0,
                "pixel {i} had depth in the last frame"
            );
        }
        let (report, expected) = (gpu.merge.unwrap(), *oracle.report());
        assert_eq!(report.merged + beyond.len(), expected.merged);
        assert_eq!(report.fresh, expected.fresh + beyond.len());
    }
}
