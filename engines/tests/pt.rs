//! `pt`, progressive differential path tracing on the GPU: the reference's estimator, so its
//! means must agree with the CPU reference within their joint noise; its invariants (Δ exactly
//! zero where the object plays no part, the same seed the same image however the samples are
//! split between frames); its accumulation (kept while still, restarted on change); and its
//! convergence rate.

mod support;

use std::sync::Arc;

use glam::{DVec3, Quat, Vec3};
use relight_core::scene::Scene;
use relight_engines::gpu::GpuContext;
use relight_engines::pt::{Pt, PtStatistics, TILE_PHASES};
use relight_engines::reference::{ReferenceSettings, render_reference};
use relight_engines::{Engine, RelitFrame, SceneFrame};
use support::{frame, load_scene, real_norm};

const SCENES: [&str; 5] = [
    "desk_box",
    "glossy_floor",
    "spot_bleed",
    "touching_wall",
    "window_env",
];

fn context() -> Arc<GpuContext> {
    Arc::new(GpuContext::new().expect("a GPU adapter (lavapipe without a GPU)"))
}

/// A `pt` with `params` over its defaults.
fn pt(ctx: &Arc<GpuContext>, params: serde_json::Value) -> Pt {
    let mut engine = Pt::new(ctx.clone()).unwrap();
    let schema = Pt::schema();
    let params = schema
        .validate(&schema.defaults(), params.as_object().unwrap())
        .unwrap();
    engine.set_params(&params);
    engine
}

fn render(engine: &mut Pt, frame: &SceneFrame) -> RelitFrame {
    let mut out = RelitFrame::default();
    engine.render(frame, &mut out).unwrap();
    out
}

fn bits(image: &relight_core::Image) -> Vec<u8> {
    let mut bytes = Vec::new();
    image.write_bytes(&mut bytes);
    bytes
}

/// Σ over pixels of a per-pixel quantity, per channel.
fn sum(values: &[Vec3]) -> DVec3 {
    values.iter().map(|v| v.as_dvec3()).sum()
}

fn sum_of_squares(values: &[Vec3]) -> DVec3 {
    values.iter().map(|v| (*v * *v).as_dvec3()).sum()
}

/// What a path tracer that shares the reference's estimator must give: per scene and channel,
/// Σ Δ over the image (pixel areas, 256 samples each) lies within 3σ of the CPU reference's,
/// σ from both renders' per-pixel standard errors (pixels are independent); pixel by pixel,
/// no more than 1 % of pixels differ by more than 4σ (heavy-tailed noise makes a few such
/// pixels possible, a wrong term makes many); and Σ L^ρ over the object's own pixels lies
/// within 3σ of the reference's.
#[test]
fn pt_agrees_with_the_reference_on_the_five_scenes() {
    let ctx = context();
    let (width, height, spp) = (32, 24, 256);
    for name in SCENES {
        let scene = Arc::new(load_scene(name));
        let mut engine = pt(&ctx, serde_json::json!({ "spp": spp }));
        render(&mut engine, &frame(scene.clone(), width, height));
        let ours: PtStatistics = engine.statistics().unwrap();
        assert_eq!(ours.spp, spp);
        let reference = render_reference(
            &scene,
            ReferenceSettings {
                spp,
                size: Some((width, height)),
                ..ReferenceSettings::default()
            },
        )
        .unwrap();
        let sigma = (sum_of_squares(&ours.delta_std_error)
            + sum_of_squares(&reference.delta_std_error))
        .map(f64::sqrt);
        let z = (sum(&ours.delta) - sum(&reference.delta)) / sigma;
        eprintln!(
            "{name}: Σ Δ pt {:.3}, reference {:.3}, z {z:.2}",
            sum(&ours.delta),
            sum(&reference.delta)
        );
        assert!(z.abs().max_element() < 3.0, "{name}: z = {z}");
        let outliers = (0..ours.delta.len())
            .filter(|&i| {
                let se = (ours.delta_std_error[i] * ours.delta_std_error[i]
                    + reference.delta_std_error[i] * reference.delta_std_error[i])
                    .map(f32::sqrt);
                (ours.delta[i] - reference.delta[i])
                    .abs()
                    .cmpgt(4.0 * se)
                    .any()
            })
            .count();
        assert!(
            outliers * 100 <= ours.delta.len(),
            "{name}: {outliers} of {} pixels beyond 4σ",
            ours.delta.len()
        );
        // The object's own pixels: L^ρ where every sample met the object. pt's per-pixel
        // variance there is the reference's (the same estimator at the same samples).
        let object: Vec<usize> = (0..ours.overlay.len())
            .filter(|&i| ours.overlay[i].w == 1.0 && reference.virtual_mask[i])
            .collect();
        let pick = |values: &[Vec3]| object.iter().map(|&i| values[i]).collect::<Vec<_>>();
        let l_rho: Vec<Vec3> = object.iter().map(|&i| ours.overlay[i].truncate()).collect();
        let sigma = (2.0 * sum_of_squares(&pick(&reference.l_rho_std_error))).map(f64::sqrt);
        let z = (sum(&l_rho) - sum(&pick(&reference.l_rho))) / sigma;
        eprintln!("{name}: object L^ρ over {} pixels, z {z:.2}", object.len());
        assert!(
            !object.is_empty() && z.abs().max_element() < 3.0,
            "{name}: object z = {z}"
        );
    }
}

/// `scene` with its virtual object(s) 100 km away: no ray of the scene can meet them.
fn object_far_away(mut scene: Scene) -> Scene {
    for mesh in scene.meshes.iter_mut().filter(|m| m.is_virtual) {
        for p in &mut mesh.positions_in_world {
            *p += Vec3::new(1e5, 0.0, 1e5);
        }
    }
    scene
}

/// Correlated sampling makes Δ exactly zero, not merely small, where the object plays no part:
/// without an object, and with one no path can reach; the composite is then the background.
#[test]
fn delta_is_exactly_zero_without_the_object_or_far_from_it() {
    let ctx = context();
    for name in ["desk_box", "window_env"] {
        let scene = load_scene(name);
        for (case, scene) in [
            ("no object", scene.without_virtual()),
            ("object 100 km away", object_far_away(scene.clone())),
        ] {
            let mut engine = pt(&ctx, serde_json::json!({ "spp": 8 }));
            let frame = frame(Arc::new(scene), 32, 24);
            let out = render(&mut engine, &frame);
            let delta = relight_engines::offline::delta_pixels(&out.delta);
            assert!(
                delta.iter().all(|d| *d == Vec3::ZERO),
                "{name}, {case}: Δ is not zero"
            );
            let background = frame.color.as_ref().unwrap();
            assert_eq!(
                bits(&out.composite),
                bits(&background.payload),
                "{name}, {case}: the composite is not the background"
            );
            assert_eq!(out.non_finite, 0);
        }
    }
}

/// Sample s of pixel i draws from its own stream: 3 + 5 samples over two frames, or tile
/// phases' shares of a sample over frames that follow a budget, are the 8 of one frame bit for
/// bit, and another seed gives another image.
#[test]
fn the_same_seed_renders_the_same_image_however_the_samples_are_split() {
    let ctx = context();
    let frame = frame(Arc::new(load_scene("spot_bleed")), 32, 24);
    let mut whole = pt(&ctx, serde_json::json!({ "spp": 8 }));
    let whole = render(&mut whole, &frame);
    let mut split = pt(&ctx, serde_json::json!({ "spp": 3, "max_spp": 8 }));
    render(&mut split, &frame);
    let mut split_params = Pt::schema().defaults();
    split_params.insert("spp".into(), 5.into());
    split_params.insert("max_spp".into(), 8.into());
    split.set_params(&split_params);
    let split = render(&mut split, &frame);
    assert_eq!(bits(&whole.delta), bits(&split.delta));
    assert_eq!(bits(&whole.composite), bits(&split.composite));
    // Shares of a sample: following a budget, the first frame traces one tile phase's.
    let mut shares = pt(&ctx, serde_json::json!({ "budget_ms": 1.0, "max_spp": 8 }));
    let first = render(&mut shares, &frame);
    assert_eq!(first.path_samples, 1.0 / f64::from(TILE_PHASES));
    assert_eq!(first.path_samples_traced, first.path_samples);
    for _ in 0..3 {
        render(&mut shares, &frame);
    }
    let mut rest = Pt::schema().defaults();
    rest.insert("spp".into(), 8.into());
    rest.insert("max_spp".into(), 8.into());
    shares.set_params(&rest);
    let shares = render(&mut shares, &frame);
    assert_eq!(shares.path_samples, 8.0);
    assert_eq!(bits(&whole.delta), bits(&shares.delta));
    assert_eq!(bits(&whole.composite), bits(&shares.composite));
    let mut other = pt(&ctx, serde_json::json!({ "spp": 8, "seed": 1 }));
    let other = render(&mut other, &frame);
    assert_ne!(bits(&whole.delta), bits(&other.delta));
}

/// The means grow while nothing changes, stop at `max_spp`, start again when the camera
/// moves by more than a quarter pixel, and ignore jitter below it.
#[test]
fn samples_accumulate_while_still_and_restart_on_change() {
    let ctx = context();
    let scene = load_scene("desk_box");
    let still = frame(Arc::new(scene.clone()), 32, 24);
    let mut engine = pt(&ctx, serde_json::json!({ "spp": 4, "max_spp": 12 }));
    for expected in [4, 8, 12, 12] {
        render(&mut engine, &still);
        assert_eq!(engine.samples(), expected);
    }
    let turned = |degrees: f32| {
        let mut moved = scene.clone();
        moved.camera.world_from_camera.rotation *= Quat::from_rotation_y(degrees.to_radians());
        frame(Arc::new(moved), 32, 24)
    };
    // 0.001° is about 0.0005 px at this size: jitter, not motion.
    render(&mut engine, &turned(0.001));
    assert_eq!(engine.samples(), 12);
    render(&mut engine, &turned(2.0));
    assert_eq!(engine.samples(), 4);
}

/// A live depth surface is compared by its revision: noise on a held surface (same revision)
/// keeps the means, a reset of the temporal merge (a new revision) restarts them.
#[test]
fn a_live_surface_restarts_the_means_only_on_a_new_revision() {
    let ctx = context();
    let mut scene = load_scene("desk_box");
    scene.surface_revision = Some(7);
    let mut engine = pt(&ctx, serde_json::json!({ "spp": 2 }));
    render(&mut engine, &frame(Arc::new(scene.clone()), 32, 24));
    let mut noisy = scene.clone();
    let real = noisy.meshes.iter_mut().find(|m| !m.is_virtual).unwrap();
    real.positions_in_world[0].y += 1e-3;
    render(&mut engine, &frame(Arc::new(noisy.clone()), 32, 24));
    assert_eq!(engine.samples(), 4);
    noisy.surface_revision = Some(8);
    render(&mut engine, &frame(Arc::new(noisy), 32, 24));
    assert_eq!(engine.samples(), 2);
}

/// Monte Carlo: four times the samples halve the standard error. Measured two ways on the
/// real pixels: the engine's own standard errors, and the distance to an independent
/// 1024-sample render (whose own noise adds about 2 % to the expected ratio).
#[test]
fn four_times_the_samples_halve_the_error() {
    let ctx = context();
    let frame = frame(Arc::new(load_scene("spot_bleed")), 48, 36);
    let mut engine = pt(&ctx, serde_json::json!({ "spp": 16 }));
    render(&mut engine, &frame);
    let at_16 = engine.statistics().unwrap();
    let mut params = Pt::schema().defaults();
    params.insert("spp".into(), 48.into());
    engine.set_params(&params);
    render(&mut engine, &frame);
    let at_64 = engine.statistics().unwrap();
    assert_eq!(at_64.spp, 64);
    let mut truth = pt(&ctx, serde_json::json!({ "spp": 1024, "seed": 99 }));
    render(&mut truth, &frame);
    let truth = truth.statistics().unwrap();
    let virtual_mask: Vec<bool> = truth.overlay.iter().map(|o| o.w != 0.0).collect();
    let rms = |values: &[Vec3]| real_norm(values, &virtual_mask);
    let estimated = rms(&at_64.delta_std_error) / rms(&at_16.delta_std_error);
    let distance = |s: &PtStatistics| {
        let d: Vec<Vec3> = s
            .delta
            .iter()
            .zip(&truth.delta)
            .map(|(a, b)| *a - *b)
            .collect();
        rms(&d)
    };
    let measured = distance(&at_64) / distance(&at_16);
    eprintln!("standard error ratio {estimated:.3}, measured error ratio {measured:.3}");
    assert!((estimated - 0.5).abs() <= 0.1, "{estimated}");
    assert!((measured - 0.5).abs() <= 0.1, "{measured}");
}
