//! The `differential` engine against the invariants of DESIGN.md and the reference path tracer's
//! direct-only Δ on the shipped scenes.

mod support;

use std::sync::Arc;

use relight_core::scene::Scene;
use support::{
    delta_of, engine, frame, load_scene, max_abs, reference_direct, relative_l2,
    virtual_moved_far_away,
};

#[test]
fn no_virtual_object_means_no_delta() {
    let scene = load_scene("desk_box").without_virtual();
    let (delta, _) = delta_of(&mut engine("differential"), &frame(Arc::new(scene), 80, 60));
    let worst = max_abs(&delta);
    assert!(worst <= 1e-6, "max |Δ| = {worst}");
}

#[test]
fn object_far_outside_the_scene_means_no_delta() {
    let scene = virtual_moved_far_away(load_scene("desk_box"));
    let (delta, _) = delta_of(&mut engine("differential"), &frame(Arc::new(scene), 80, 60));
    let worst = max_abs(&delta);
    assert!(worst <= 1e-6, "max |Δ| = {worst}");
}

/// The engine's shadows come from shadow maps of one texel per sample, so pixels that a shadow
/// boundary crosses may be lit in one and shadowed in the other: those pixels (a reference
/// neighbour differing by more than 5 % of the largest |Δ|) are excluded pixel-wise and only
/// bound the overall relative L2 (‖edge‖ / ‖shadow‖ ≈ √(edge pixels / shadow pixels) ≲ 0.15 at
/// 160 × 120). Every other real pixel must agree within 4 standard errors of the reference plus
/// one f16 step of Δ (2⁻¹⁰ relative: rounding plus the rasteriser's interpolated positions).
#[test]
fn matches_the_reference_direct_delta() {
    for name in ["desk_box", "spot_bleed", "touching_wall", "glossy_floor"] {
        let scene: Scene = load_scene(name);
        let (w, h) = (160, 120);
        let reference = reference_direct(&scene, w, h, 64);
        let (delta, _) = delta_of(&mut engine("differential"), &frame(Arc::new(scene), w, h));
        let (error, _) = relative_l2(&delta, &reference.delta, &reference.virtual_mask);
        let edges = support::edge_pixels(&reference.delta, w as usize, h as usize, 0.05);
        let mut bad = 0;
        for i in 0..delta.len() {
            if reference.virtual_mask[i] || edges[i] {
                continue;
            }
            let r = reference.delta[i];
            let tolerance = 4.0 * reference.delta_std_error[i] + r.abs() * 2f32.powi(-10) + 1e-5;
            if ((delta[i] - r).abs() - tolerance).max_element() > 0.0 {
                bad += 1;
            }
        }
        eprintln!("{name}: relative L2 {error:.4}, {bad} pixels off the edges disagree");
        assert!(error < 0.15, "{name}: relative L2 {error}");
        assert_eq!(bad, 0, "{name}");
    }
}

/// A lost device is an error, not a panic, and the shared context hands out a fresh device, on
/// which a rebuilt engine renders again (what the pipeline does after a loss).
#[test]
fn a_lost_device_is_an_error_and_a_rebuilt_engine_renders_again() {
    use relight_engines::differential::Differential;
    use relight_engines::gpu::{GpuError, SharedGpu};
    use relight_engines::{Engine, EngineError, RelitFrame};

    let shared = SharedGpu::default();
    let ctx = shared.get().unwrap();
    let scene = Arc::new(load_scene("desk_box"));
    let frame = frame(scene, 32, 24);
    let mut engine = Differential::new(ctx.clone()).unwrap();
    let mut out = RelitFrame::default();
    engine.render(&frame, &mut out).unwrap();
    ctx.device.destroy();
    let err = engine.render(&frame, &mut out).unwrap_err();
    assert!(
        matches!(err, EngineError::Gpu(GpuError::Lost { .. })),
        "{err}"
    );
    let fresh = shared.get().unwrap();
    assert!(!Arc::ptr_eq(&ctx, &fresh), "a new device after the loss");
    let mut rebuilt = Differential::new(fresh).unwrap();
    rebuilt.render(&frame, &mut out).unwrap();
}

/// An environment-only scene: the map is cut into directional lights, so the object is lit and
/// casts the window's shadow (before, both were missing: Δ = 0 and a black object). Judged
/// against the direct-only reference; 8 lights stand for the whole sky, so a share of the
/// error is that discretisation, the rest pixel-centre edges and noise.
#[test]
fn an_environment_only_scene_lights_the_object_and_casts_its_shadow() {
    let scene = load_scene("window_env");
    let (w, h) = (80, 60);
    let reference = reference_direct(&scene, w, h, 32);
    let (delta, relit) = delta_of(&mut engine("differential"), &frame(Arc::new(scene), w, h));
    let (error, _) = relative_l2(&delta, &reference.delta, &reference.virtual_mask);
    let object = relight_engines::offline::object_error(
        &relit.composite,
        &reference.l_rho,
        &reference.virtual_mask,
    )
    .expect("the object is in view");
    eprintln!("window_env: Δ relative L2 {error:.4}, object relative L2 {object:.4}");
    // Measured 0.23 and 0.23 at this size (a black object or no shadow scores 1.0): the
    // silhouette is a large share of the object's pixels at 80 × 60.
    assert!(error < 0.4, "Δ relative L2 {error}");
    assert!(object < 0.35, "object relative L2 {object}");
}

/// A box sunk 2 mm into the floor (a live pose a little off does that) must not show through
/// the floor along its foot. With the camera's depth forward and its near plane at 1e-4 of its
/// far one, an f32 depth stepped by 0.5 mm at desk_box's 2 m and the sunk face won the depth
/// test over the floor in front of it: 20 floor pixels along its foot read the box's light, Δ
/// −0.33 where the box on the floor reads 0 (Δ L2 0.26 → 0.88 against the reference).
/// Reversed, they read as the floor: no pixel goes from no change to dark but where the shadow
/// moved.
#[test]
fn a_box_sunk_into_the_floor_does_not_show_through_it() {
    let desk = Arc::new(load_scene("desk_box"));
    let mut sunk = (*desk).clone();
    for mesh in sunk.meshes.iter_mut().filter(|m| m.is_virtual) {
        for p in &mut mesh.positions_in_world {
            p.y -= 0.002;
        }
    }
    let mut engine = engine("differential");
    let (on_floor, _) = delta_of(&mut engine, &frame(desk, 160, 120));
    let (into_floor, _) = delta_of(&mut engine, &frame(Arc::new(sunk), 160, 120));
    let darkened = on_floor
        .iter()
        .zip(&into_floor)
        .filter(|(a, b)| a.abs().max_element() < 0.01 && b.max_element() < -0.1)
        .count();
    assert!(darkened <= 4, "{darkened} pixels went dark");
}
