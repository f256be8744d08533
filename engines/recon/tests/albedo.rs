//! Diffuse albedo (DLPV eq. 1) on the simulated rig, scored against its ground truth: relative
//! error ‖k_d − k_d,true‖ / ‖k_d,true‖ on the lit diffuse pixels it estimates, per frame and
//! after temporal smoothing; what skipping shadows and highlights is worth; and the bias that
//! the unmodelled interreflections of a closed room leave.
//!
//! Run with `--nocapture` to see the measured numbers.

mod depth_common;

use depth_common::*;
use glam::Vec3;
use relight_core::scene::Scene;
use relight_recon::albedo::{
    AlbedoEstimator, AlbedoFrame, AlbedoInput, AlbedoSettings, ColorDecoding, PixelClass,
    ShadowQuery,
};
use relight_recon::temporal::TemporalMerge;
use relight_reference::accel::Geometry;

/// Mean and median relative error, signed mean error per channel, and the pixel count, over
/// the pixels `albedo` holds that this frame estimated and whose truth is diffuse (or, with
/// `glossy_too`, any surface).
fn errors(
    albedo: &[Option<Vec3>],
    frame: &AlbedoFrame,
    data: &SimData,
    glossy_too: bool,
) -> (f32, f32, Vec3, usize) {
    let mut relative = Vec::new();
    let mut signed = Vec3::ZERO;
    for (k, a) in albedo.iter().enumerate() {
        let Some(a) = a else { continue };
        if frame.class[k] != PixelClass::Estimated || (data.truth_specular[k] > 0.0 && !glossy_too)
        {
            continue;
        }
        let truth = data.truth_albedo[k];
        relative.push((*a - truth).length() / truth.length());
        signed += (*a - truth) / truth;
    }
    let n = relative.len();
    let (mean, median) = mean_median(relative);
    (mean, median, signed / n.max(1) as f32, n)
}

struct Run {
    first_frame: (f32, f32, Vec3, usize),
    last_frame: (f32, f32, Vec3, usize),
    smoothed: (f32, f32, Vec3, usize),
    last: AlbedoFrame,
}

/// `frames` static frames of `scene` through depth reconstruction and the estimator; shadow
/// rays against the real scene's meshes when `shadows`.
fn run(
    scene: &Scene,
    settings: AlbedoSettings,
    shadows: bool,
    frames: u32,
    glossy_too: bool,
) -> Run {
    let rig = rig(scene, None, frames);
    let camera = *rig.camera();
    let real = Geometry::new(&scene.without_virtual(), false);
    let decoding = ColorDecoding::from_table(
        &rig.settings().response.inverse_table(),
        rig.settings().exposure,
    )
    .unwrap();
    let mut merge = TemporalMerge::new(temporal_settings(&camera));
    let mut estimator = AlbedoEstimator::new(settings, decoding);
    let visibility = |q: &ShadowQuery| {
        if !shadows {
            return 1.0;
        }
        let origin = q.point_in_world + q.normal_in_world * 0.01;
        let blocked = real
            .intersect(
                origin,
                q.incident.direction_to_light,
                0.0,
                q.incident.distance_m - 0.01,
            )
            .is_some();
        if blocked { 0.0 } else { 1.0 }
    };
    let mut first_frame = None;
    let mut last = None;
    for i in 0..frames {
        let data = sim_data(&rig, i);
        let r = reconstruct(&data, &camera, &mut merge);
        let input = AlbedoInput {
            color: &data.color,
            positions: &r.positions,
            normals: &r.normals,
            camera: &camera,
            world_from_camera: data.world_from_camera,
            lights: &data.lights,
            indirect_irradiance: &[],
        };
        let frame = estimator.estimate(&input, visibility).unwrap();
        if i == 0 {
            first_frame = Some(errors(&frame.this_frame, &frame, &data, glossy_too));
        }
        last = Some((data, frame));
    }
    let (data, frame) = last.unwrap();
    Run {
        first_frame: first_frame.unwrap(),
        last_frame: errors(&frame.this_frame, &frame, &data, glossy_too),
        smoothed: errors(&frame.albedo, &frame, &data, glossy_too),
        last: frame,
    }
}

fn describe(name: &str, run: &Run) {
    let f = |e: &(f32, f32, Vec3, usize)| {
        format!(
            "mean {:.1} %, median {:.1} %, bias ({:+.1}, {:+.1}, {:+.1}) % over {} px",
            e.0 * 100.0,
            e.1 * 100.0,
            e.2.x * 100.0,
            e.2.y * 100.0,
            e.2.z * 100.0,
            e.3
        )
    };
    println!(
        "{name}: frame 0 {}; last frame alone {}; smoothed {}; census {:?}",
        f(&run.first_frame),
        f(&run.last_frame),
        f(&run.smoothed),
        run.last.census
    );
}

/// The spot_bleed floor with its box made real: the box's shadow on the floor is skipped by
/// the shadow rays; the floor reflects nothing back (one plane and a box, little
/// interreflection), so eq. 1's assumption holds.
#[test]
fn albedo_of_lit_diffuse_pixels_matches_the_truth() {
    let mut scene = load_scene("spot_bleed");
    scene.meshes.iter_mut().for_each(|m| m.is_virtual = false);
    let with_shadows = run(&scene, AlbedoSettings::default(), true, 6, false);
    describe("spot_bleed, real box, shadow rays", &with_shadows);
    let blind = run(&scene, AlbedoSettings::default(), false, 6, false);
    describe("spot_bleed, real box, no shadow test", &blind);
    let floor_only = run(
        &load_scene("spot_bleed"),
        AlbedoSettings::default(),
        true,
        6,
        false,
    );
    describe("spot_bleed (floor only)", &floor_only);

    for r in [&with_shadows, &floor_only] {
        assert!(
            r.first_frame.3 > 5000,
            "most lit floor pixels are estimated"
        );
        assert!(
            r.first_frame.0 < 0.08 && r.first_frame.1 < 0.06,
            "{:?}",
            r.first_frame
        );
        assert!(
            r.first_frame.2.abs().max_element() < 0.03,
            "no bias: {:?}",
            r.first_frame
        );
        assert!(
            r.smoothed.0 < 0.75 * r.last_frame.0,
            "smoothing averages the noise"
        );
        assert!(
            r.smoothed.0 < 0.05 && r.smoothed.1 < 0.03,
            "{:?}",
            r.smoothed
        );
    }
    assert!(
        with_shadows.last.census.shadowed > 500,
        "the box's shadow is skipped"
    );
    // Shadowed pixels taken as lit come out far too dark.
    assert!(with_shadows.first_frame.0 < 0.7 * blind.first_frame.0);
    assert!(blind.first_frame.2.max_element() < -0.02);
}

/// glossy_floor: k_d = 0.5, k_s = 0.4, Phong n = 200 under a point light. Away from the mirror
/// direction of the light the floor is diffuse; near it eq. 1 would read the highlight as
/// albedo.
#[test]
fn highlights_are_skipped_on_a_glossy_floor() {
    let scene = load_scene("glossy_floor");
    let skipping = run(&scene, AlbedoSettings::default(), false, 4, true);
    describe("glossy_floor, highlights skipped", &skipping);
    let naive = AlbedoSettings {
        highlight_cone_rad: 0.0,
        max_albedo: f32::MAX,
        saturated_code: 255,
        ..AlbedoSettings::default()
    };
    let not_skipping = run(&scene, naive, false, 4, true);
    describe("glossy_floor, nothing skipped", &not_skipping);
    let census = skipping.last.census;
    assert!(
        census.highlight > 500 && census.saturated > 100,
        "{census:?}"
    );
    assert!(skipping.first_frame.0 < 0.1, "{:?}", skipping.first_frame);
    assert!(not_skipping.first_frame.0 > 3.0 * skipping.first_frame.0);
}

/// desk_box is a closed room of 0.75-albedo walls lit from inside: a large part of each
/// pixel's light has bounced off the other walls, which eq. 1 (direct light only) reads as
/// albedo. The estimate is biased up by that share, and pixels whose indirect light exceeds a
/// quarter of their direct light come out above 1 and are skipped. This is the method's known
/// limit, measured here so a change that moves it shows.
#[test]
fn interreflections_bias_the_estimate_upwards() {
    let scene = load_scene("desk_box");
    let r = run(&scene, AlbedoSettings::default(), true, 3, false);
    describe("desk_box (closed room)", &r);
    let touching = run(
        &load_scene("touching_wall"),
        AlbedoSettings::default(),
        true,
        3,
        false,
    );
    describe("touching_wall (floor and one wall)", &touching);
    assert!(
        r.first_frame.2.min_element() > 0.05 && r.first_frame.0 < 0.3,
        "{:?}",
        r.first_frame
    );
    assert!(touching.first_frame.2.min_element() > 0.0 && touching.first_frame.0 < 0.15);
    assert!(r.last.census.above_one > r.last.census.estimated / 2);
}
