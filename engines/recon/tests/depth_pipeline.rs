//! Depth → geometry on the simulated rig, scored against its ground truth: depth RMSE of the raw
//! Kinect frames, after the guided filter and after the temporal merge; normal angular error;
//! a pose jump that must reset the merge rather than smear two views together; a shaking
//! hand-held camera.
//!
//! Run with `--nocapture` to see the measured numbers.

mod depth_common;

use depth_common::*;
use relight_core::scene::Scene;
use relight_recon::depth::{DepthMap, DepthRange, guided_filter};
use relight_recon::normals::{NormalMap, NormalSettings, normals, positions};
use relight_recon::temporal::{ResetReason, TemporalMerge, TemporalSettings};
use relight_sim::rig::CameraPath;
use relight_sim::trajectory::Trajectory;

/// The spot_bleed scene with its box made real: a depth edge with a colour edge, projector
/// shadows beside it and a cast shadow.
fn spot_bleed_with_real_box() -> Scene {
    let mut scene = load_scene("spot_bleed");
    scene.meshes.iter_mut().for_each(|m| m.is_virtual = false);
    scene
}

/// Angular errors (degrees) of `normals` against the world-frame truth, where both exist.
fn angular_errors(normals: &NormalMap, data: &SimData) -> (f32, f32, usize) {
    let errors: Vec<f32> = normals
        .in_world(&data.world_from_camera)
        .iter()
        .zip(&data.truth_normals)
        .filter_map(|(n, t)| {
            Some(
                n.as_ref()?
                    .dot(*t.as_ref()?)
                    .clamp(-1.0, 1.0)
                    .acos()
                    .to_degrees(),
            )
        })
        .collect();
    let count = errors.len();
    let (mean, median) = mean_median(errors);
    (mean, median, count)
}

fn normals_of(
    depth: &DepthMap,
    data: &SimData,
    rig: &relight_sim::rig::SimRig,
) -> (f32, f32, usize) {
    let map = normals(
        &positions(depth, rig.camera()).unwrap(),
        &NormalSettings::default(),
    );
    angular_errors(&map, data)
}

#[test]
fn filtering_then_merging_lowers_depth_error_on_a_static_camera() {
    let frames = 6;
    let scenes = [
        ("desk_box", load_scene("desk_box")),
        ("touching_wall", load_scene("touching_wall")),
        ("spot_bleed", load_scene("spot_bleed")),
        ("spot_bleed, real box", spot_bleed_with_real_box()),
    ];
    for (name, scene) in scenes {
        let rig = rig(&scene, None, frames);
        let camera = *rig.camera();
        let mut merge = TemporalMerge::new(temporal_settings(&camera));
        let mut last = None;
        for i in 0..frames {
            let data = sim_data(&rig, i);
            let reconstructed = reconstruct(&data, &camera, &mut merge);
            last = Some((data, reconstructed));
        }
        let (data, r) = last.unwrap();
        // Pixels the sensor measured and that have a true surface.
        let mask: Vec<bool> = r
            .raw
            .metres
            .iter()
            .zip(&data.truth_depth)
            .map(|(z, t)| *z > 0.0 && *t > 0.0)
            .collect();
        let (raw, n) = rmse(&r.raw, &data.truth_depth, &mask);
        let (filtered, _) = rmse(&r.filtered, &data.truth_depth, &mask);
        let (merged, _) = rmse(&r.merged, &data.truth_depth, &mask);
        let normal_raw = normals_of(&r.raw, &data, &rig);
        let normal_filtered = normals_of(&r.filtered, &data, &rig);
        let normal_merged = angular_errors(&r.normals, &data);
        println!(
            "{name}: {n} px; depth RMSE raw {:.2} mm, guided {:.2} mm, merged ({frames} frames) \
             {:.2} mm; normal error mean/median raw {:.2}°/{:.2}°, guided {:.2}°/{:.2}°, \
             merged {:.2}°/{:.2}° ({} px)",
            raw * 1e3,
            filtered * 1e3,
            merged * 1e3,
            normal_raw.0,
            normal_raw.1,
            normal_filtered.0,
            normal_filtered.1,
            normal_merged.0,
            normal_merged.1,
            normal_merged.2,
        );
        assert!(
            filtered < 0.75 * raw,
            "{name}: guided {filtered} vs raw {raw}"
        );
        assert!(
            merged < 0.97 * filtered,
            "{name}: merged {merged} vs guided {filtered}"
        );
        assert!(normal_filtered.0 < normal_raw.0 && normal_merged.0 < normal_filtered.0);
        assert!(
            normal_merged.1 < 1.5,
            "{name}: median normal error {}",
            normal_merged.1
        );
        assert!(
            normal_merged.0 < 8.0,
            "{name}: mean normal error {}",
            normal_merged.0
        );
        // No geometry where the sensor saw none, and none lost where it did.
        for (m, raw) in r.merged.metres.iter().zip(&r.raw.metres) {
            assert_eq!(*m > 0.0, *raw > 0.0);
            assert!(m.is_finite());
        }
    }
}

#[test]
fn a_pose_jump_resets_the_merge_to_the_current_frame() {
    let scene = load_scene("desk_box");
    let rig = rig(&scene, Some(CameraPath::Orbit.trajectory(&scene)), 60);
    let camera = *rig.camera();
    let mut merge = TemporalMerge::new(temporal_settings(&camera));
    for i in [0, 1, 2, 3] {
        let data = sim_data(&rig, i);
        reconstruct(&data, &camera, &mut merge);
        assert_eq!(
            merge.report().reset.is_some(),
            i == 0,
            "frame {i}: {:?}",
            merge.report()
        );
    }
    // 45 frames later the orbit has turned 27° and moved about 0.9 m.
    let data = sim_data(&rig, 48);
    let raw = DepthMap::from_image(&data.depth, DepthRange::default()).unwrap();
    let filtered = guided_filter(&raw, &data.color, &filter_settings(&camera)).unwrap();
    let merged = merge
        .merge(&filtered, &camera, &data.world_from_camera)
        .unwrap();
    let Some(ResetReason::PoseJump {
        translation_m,
        rotation_rad,
    }) = merge.report().reset
    else {
        panic!("expected a pose-jump reset, got {:?}", merge.report());
    };
    println!(
        "pose jump of {translation_m:.2} m / {:.1}°: {:?}",
        rotation_rad.to_degrees(),
        merge.report()
    );
    assert!(translation_m > 0.5 && rotation_rad > 20f32.to_radians());
    assert_eq!(
        merged, filtered,
        "after the jump the output is the current frame's, unblended"
    );
    // The next frame continues from the reset history.
    let data = sim_data(&rig, 49);
    reconstruct(&data, &camera, &mut merge);
    assert_eq!(merge.report().reset, None);
    assert!(
        merge.report().merged > merge.report().rejected * 10,
        "{:?}",
        merge.report()
    );
}

/// Tracking lost: the camera moved but its reported pose did not. The warp by the stale pose
/// puts history on the wrong pixels; most of it disagrees with the current depth, and the merge
/// restarts instead of averaging two views.
#[test]
fn a_stale_pose_is_caught_by_disagreement() {
    let scene = load_scene("desk_box");
    let rig = rig(&scene, Some(CameraPath::Orbit.trajectory(&scene)), 60);
    let camera = *rig.camera();
    let settings = temporal_settings(&camera);
    let mut merge = TemporalMerge::new(settings);
    let mut blind = TemporalMerge::new(TemporalSettings {
        max_translation_m: f32::MAX,
        max_rotation_rad: f32::MAX,
        min_agreement: 0.0,
        ..settings
    });
    let stale_pose = rig.world_from_camera(0);
    let mut filtered_now = None;
    for i in [0, 1, 2, 48] {
        let data = sim_data(&rig, i);
        let raw = DepthMap::from_image(&data.depth, DepthRange::default()).unwrap();
        let filtered = guided_filter(&raw, &data.color, &filter_settings(&camera)).unwrap();
        let merged = merge.merge(&filtered, &camera, &stale_pose).unwrap();
        let blended = blind.merge(&filtered, &camera, &stale_pose).unwrap();
        filtered_now = Some((data, filtered, merged, blended));
    }
    let (data, filtered, merged, blended) = filtered_now.unwrap();
    let Some(ResetReason::Disagreement { agreement }) = merge.report().reset else {
        panic!("expected a disagreement reset, got {:?}", merge.report());
    };
    assert_eq!(merged, filtered);
    let mask: Vec<bool> = filtered
        .metres
        .iter()
        .zip(&data.truth_depth)
        .map(|(z, t)| *z > 0.0 && *t > 0.0)
        .collect();
    let (reset_rmse, _) = rmse(&merged, &data.truth_depth, &mask);
    let (blended_rmse, _) = rmse(&blended, &data.truth_depth, &mask);
    println!(
        "stale pose: agreement {agreement:.2}; RMSE after the reset {:.2} mm, merged without \
         resets {:.2} mm ({:?})",
        reset_rmse * 1e3,
        blended_rmse * 1e3,
        blind.report()
    );
    assert!(blended_rmse > reset_rmse);
}

#[test]
fn a_shaking_camera_is_merged_without_smearing() {
    let scene = load_scene("touching_wall");
    let trajectory: Trajectory = CameraPath::Shake.trajectory(&scene);
    let frames = 6;
    let rig = rig(&scene, Some(trajectory), frames);
    let camera = *rig.camera();
    let mut merge = TemporalMerge::new(temporal_settings(&camera));
    for i in 0..frames {
        let data = sim_data(&rig, i);
        let r = reconstruct(&data, &camera, &mut merge);
        if i == frames - 1 {
            let mask: Vec<bool> = r
                .raw
                .metres
                .iter()
                .zip(&data.truth_depth)
                .map(|(z, t)| *z > 0.0 && *t > 0.0)
                .collect();
            let (raw, _) = rmse(&r.raw, &data.truth_depth, &mask);
            let (filtered, _) = rmse(&r.filtered, &data.truth_depth, &mask);
            let (merged, _) = rmse(&r.merged, &data.truth_depth, &mask);
            let normal = angular_errors(&r.normals, &data);
            println!(
                "shaking camera (1 cm, 0.5°): RMSE raw {:.2} mm, guided {:.2} mm, merged {:.2} mm; \
                 normals {:.2}°/{:.2}°; {:?}",
                raw * 1e3,
                filtered * 1e3,
                merged * 1e3,
                normal.0,
                normal.1,
                merge.report()
            );
            assert_eq!(merge.report().reset, None);
            assert!(merged < filtered, "merged {merged} vs guided {filtered}");
        }
    }
}
