//! Edges converged over still frames (`Deferred`'s accumulation, every GPU engine): the first
//! frame after a change is the pixel-centre picture, still frames average sub-pixel samples
//! towards the pixel's area, and the composite always takes the frame's own background.

mod support;

use std::sync::Arc;

use glam::{Quat, Vec3};
use relight_core::scene::Scene;
use relight_core::{Frame, Image, PixelFormat};
use relight_engines::offline::{composite_pixels as linear, delta_pixels};
use relight_engines::{Engine, RelitFrame, SceneFrame};
use support::{engine_with, frame, load_scene};

fn render(engine: &mut Box<dyn Engine>, frame: &SceneFrame) -> RelitFrame {
    let mut out = RelitFrame::default();
    engine
        .render(frame, &mut out)
        .unwrap_or_else(|e| panic!("{e}"));
    out
}

fn with(params: &serde_json::Value, accumulate: u32) -> serde_json::Value {
    let mut params = params.clone();
    params["accumulate"] = accumulate.into();
    params
}

fn turned_camera(scene: &Scene) -> Scene {
    let mut scene = scene.clone();
    let pose = &mut scene.camera.world_from_camera;
    pose.rotation = Quat::from_rotation_y(0.02) * pose.rotation;
    scene
}

/// Every engine: with accumulation on, the first frame and the first after the camera moved
/// are bit-identical to the same engine's without it, and the still frames between differ.
#[test]
fn the_first_frame_after_a_change_is_the_pixel_centre_picture() {
    let desk = Arc::new(load_scene("desk_box"));
    let turned = Arc::new(turned_camera(&desk));
    let frames = [&desk, &desk, &desk, &turned].map(|s| frame(s.clone(), 64, 48));
    let small = serde_json::json!({ "volume_size": 16, "steps": 8 });
    for (name, params) in [
        ("differential", serde_json::json!({})),
        ("dlpv", small),
        ("dvct", serde_json::json!({ "volume_size": 16 })),
        ("dir", serde_json::json!({ "vpl_count": 64 })),
        ("ibl", serde_json::json!({ "map_size": 16 })),
    ] {
        let mut accumulating = engine_with(name, with(&params, 8));
        let mut single = engine_with(name, with(&params, 1));
        for (i, frame) in frames.iter().enumerate() {
            let a = render(&mut accumulating, frame);
            let b = render(&mut single, frame);
            assert_eq!(same_picture(&a, &b), i == 0 || i == 3, "{name}: frame {i}");
        }
    }
}

/// `image` (`factor`·w × `factor`·h) averaged over `factor` × `factor` blocks.
fn box_filtered(pixels: &[Vec3], width: usize, factor: usize) -> Vec<Vec3> {
    let (w, h) = (width / factor, pixels.len() / width / factor);
    let mut out = vec![Vec3::ZERO; w * h];
    for (i, p) in pixels.iter().enumerate() {
        let (x, y) = (i % width / factor, i / width / factor);
        out[y * w + x] += *p / (factor * factor) as f32;
    }
    out
}

fn relative_l2(a: &[Vec3], b: &[Vec3]) -> f64 {
    let (mut err, mut norm) = (0.0f64, 0.0f64);
    for (x, y) in a.iter().zip(b) {
        err += f64::from((*x - *y).length_squared());
        norm += f64::from(y.length_squared());
    }
    (err / norm).sqrt()
}

/// `differential` on the desk at 40 × 30, where shadow and silhouette edges cover much of the
/// picture: 32 accumulated frames against the same engine's 8×-supersampled picture, box
/// filtered to 40 × 30 (its own pixel-area truth, free of any reference noise). The centre
/// samples miss it by the edges' steps; 32 Halton points leave a residue of the order of 1/32
/// of a step on edge pixels (the supersampled truth's own 1/64), so the accumulated error of Δ
/// must fall below a quarter of the single frame's (measured: 0.40 to 0.06). The composite,
/// whose object silhouette blends the object over the background by its coverage, has a floor
/// of 8-bit quantisation besides, so below 0.4 of it (measured: 0.056 to 0.013).
#[test]
fn still_frames_converge_to_the_pixel_area() {
    let desk = Arc::new(load_scene("desk_box"));
    let (w, h, factor) = (40u32, 30u32, 8u32);
    let mut truth_engine = engine_with("differential", serde_json::json!({ "accumulate": 1 }));
    let truth = render(
        &mut truth_engine,
        &frame(desk.clone(), w * factor, h * factor),
    );
    let truth_delta = box_filtered(&delta_pixels(&truth.delta), (w * factor) as usize, 8);
    let truth_composite = box_filtered(&linear(&truth.composite), (w * factor) as usize, 8);

    let mut engine = engine_with("differential", serde_json::json!({ "accumulate": 32 }));
    let small = frame(desk, w, h);
    let first = render(&mut engine, &small);
    let mut last = first.clone();
    for _ in 1..32 {
        last = render(&mut engine, &small);
    }
    let single = relative_l2(&delta_pixels(&first.delta), &truth_delta);
    let accumulated = relative_l2(&delta_pixels(&last.delta), &truth_delta);
    assert!(single > 0.05, "the case must have edges: {single}");
    assert!(
        accumulated < 0.25 * single,
        "Δ: accumulated {accumulated} vs single frame {single}"
    );
    let single = relative_l2(&linear(&first.composite), &truth_composite);
    let accumulated = relative_l2(&linear(&last.composite), &truth_composite);
    assert!(
        accumulated < 0.4 * single,
        "composite: accumulated {accumulated} vs single frame {single}"
    );
    // Complete after 32 frames: the mean is kept, not drifted by more samples.
    let kept = render(&mut engine, &small);
    assert!(same_picture(&kept, &last));
}

/// Whether two frames show the same picture: Δ and the composite, bit for bit.
fn same_picture(a: &RelitFrame, b: &RelitFrame) -> bool {
    a.delta == b.delta && a.composite == b.composite
}

/// `frame` with a camera image of one grey `level` instead.
fn with_background(frame: SceneFrame, level: u8) -> SceneFrame {
    let (width, height) = frame
        .color
        .as_ref()
        .map_or((0, 0), |c| (c.payload.width(), c.payload.height()));
    let mut image = Image::new(width, height, PixelFormat::Rgb8);
    image.as_u8_mut().unwrap().fill(level);
    SceneFrame {
        color: Some(Arc::new(Frame::new(1, frame.stamp, image))),
        ..frame
    }
}

/// The background is not averaged: a still scene whose camera image changes (the live video)
/// shows the new image at once wherever the object changes nothing.
#[test]
fn the_composite_takes_each_frames_background() {
    let desk = Arc::new(load_scene("desk_box"));
    let mut engine = engine_with("differential", serde_json::json!({ "accumulate": 8 }));
    let grey = frame(desk.clone(), 64, 48);
    for _ in 0..4 {
        render(&mut engine, &grey);
    }
    let out = render(&mut engine, &with_background(grey, 200));
    let delta = delta_pixels(&out.delta);
    let untouched: Vec<&[u8]> = out
        .composite
        .as_u8()
        .unwrap()
        .chunks_exact(3)
        .zip(&delta)
        .filter(|(_, d)| **d == Vec3::ZERO)
        .map(|(c, _)| c)
        .collect();
    assert!(untouched.len() > 64 * 48 / 4, "{}", untouched.len());
    for c in untouched {
        assert!(c.iter().all(|&v| v.abs_diff(200) <= 1), "{c:?}");
    }
}

/// Whether `out`'s frame drew anything besides the shading pass (its work rows: one per pass
/// run, `RelitFrame::work`).
fn drew(out: &RelitFrame) -> bool {
    out.work.iter().any(|w| w.pass != "shade")
}

/// Every engine: once the mean of `accumulate` still frames is complete, a frame whose inputs
/// have not changed draws nothing (no G-buffer, no map, no pass of the engine's own; only the
/// shading pass, which keeps the mean) and shows the mean bit for bit over its own background.
#[test]
fn a_complete_mean_is_held_without_drawing() {
    let desk = Arc::new(load_scene("desk_box"));
    let window = Arc::new(load_scene("window_env"));
    let small = serde_json::json!({ "volume_size": 16, "steps": 8 });
    for (name, params, scene) in [
        ("differential", serde_json::json!({}), &desk),
        ("dlpv", small, &desk),
        ("dvct", serde_json::json!({ "volume_size": 16 }), &desk),
        ("dir", serde_json::json!({ "vpl_count": 64 }), &desk),
        ("ibl", serde_json::json!({ "map_size": 16 }), &window),
    ] {
        let mut engine = engine_with(name, with(&params, 4));
        let grey = frame(scene.clone(), 64, 48);
        let outs: Vec<RelitFrame> = (0..6).map(|_| render(&mut engine, &grey)).collect();
        for (i, out) in outs.iter().enumerate() {
            assert_eq!(drew(out), i < 4, "{name}: frame {i}: {:?}", out.work);
        }
        for held in &outs[4..] {
            assert!(same_picture(held, &outs[3]), "{name}");
        }
        // The live video still shows through a held frame.
        let out = render(&mut engine, &with_background(grey, 200));
        assert!(!drew(&out) && out.delta == outs[3].delta, "{name}");
        assert_ne!(out.composite, outs[3].composite, "{name}");
    }
}

/// `scene` with its real meshes moved by `offset_m` along y, as sensor noise moves a live depth
/// surface between frames, and the given [`Scene::surface_revision`].
fn noisy_surface(scene: &Scene, offset_m: f32, revision: Option<u64>) -> Arc<Scene> {
    let mut scene = scene.clone();
    for mesh in scene.meshes.iter_mut().filter(|m| !m.is_virtual) {
        for p in &mut mesh.positions_in_world {
            p.y += offset_m;
        }
    }
    scene.surface_revision = revision;
    Arc::new(scene)
}

/// A live depth surface counts as unchanged while the depth merge keeps its revision, so its
/// frame-to-frame noise is averaged into the mean, which then holds; a new revision (the merge
/// reset) starts the mean afresh. A scene file's geometry, which has no revision, is compared
/// by content: moved by as little, it starts the mean on every frame.
#[test]
fn a_live_surface_is_still_while_its_revision_holds() {
    let desk = load_scene("desk_box");
    let mut accumulating = engine_with("differential", serde_json::json!({ "accumulate": 4 }));
    let mut single = engine_with("differential", serde_json::json!({ "accumulate": 1 }));
    let offsets = [0.0, 1e-4, -1e-4, 2e-4, 0.0, 1e-4];
    for (revision, first_alone) in [(Some(1), [true, false, false, false]), (None, [true; 4])] {
        for (i, offset) in offsets.iter().enumerate() {
            let f = frame(noisy_surface(&desk, *offset, revision), 64, 48);
            let a = render(&mut accumulating, &f);
            let b = render(&mut single, &f);
            if i < 4 {
                assert_eq!(
                    same_picture(&a, &b),
                    first_alone[i],
                    "{revision:?}: frame {i}"
                );
            }
            assert_eq!(
                drew(&a),
                revision.is_none() || i < 4,
                "{revision:?}: frame {i}"
            );
        }
    }
    // The merge resets: revision 2 is a new surface, shown alone.
    let f = frame(noisy_surface(&desk, 0.0, Some(2)), 64, 48);
    let (a, b) = (render(&mut accumulating, &f), render(&mut single, &f));
    assert!(same_picture(&a, &b) && drew(&a));
}

/// A tracked camera's jitter below a quarter pixel of image motion is no change: the mean goes
/// on, drawn from the held pose. A turn of a pixel starts it afresh.
#[test]
fn camera_jitter_below_a_quarter_pixel_keeps_the_mean() {
    let desk = load_scene("desk_box");
    let height = 48u32;
    let focal_px = height as f32 / (2.0 * (desk.camera.yfov_rad / 2.0).tan());
    let turned = |px: f32| {
        let mut scene = desk.clone();
        let pose = &mut scene.camera.world_from_camera;
        pose.rotation = Quat::from_rotation_y(px / focal_px) * pose.rotation;
        Arc::new(scene)
    };
    let mut accumulating = engine_with("differential", serde_json::json!({ "accumulate": 8 }));
    let mut single = engine_with("differential", serde_json::json!({ "accumulate": 1 }));
    let base = frame(Arc::new(desk.clone()), 64, height);
    render(&mut accumulating, &base);
    let jittered = frame(turned(0.1), 64, height);
    let a = render(&mut accumulating, &jittered);
    // Drawn from the held pose at the second Halton offset: neither the jittered camera's
    // centre picture nor the held one's.
    for reference in [&jittered, &base] {
        let b = render(&mut single, reference);
        assert!(a.delta != b.delta, "accumulated, not shown alone");
    }
    let moved = frame(turned(1.0), 64, height);
    let (a, b) = (
        render(&mut accumulating, &moved),
        render(&mut single, &moved),
    );
    assert!(same_picture(&a, &b), "a pixel's turn is a change");
}
