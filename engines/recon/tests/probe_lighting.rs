//! `ProbeLighting` on the simulated rig's probe stream: an estimate after each full bracket, in
//! absolute radiance through the calibration's scale, with the lights where the simulator put
//! them.

use std::sync::Arc;

use glam::Vec3;
use relight_core::scene::Scene;
use relight_core::{Frame, ProbeImage, StreamMessage};
use relight_recon::probe::{ProbeLighting, ProbeSettings};
use relight_sim::rig::{SimRig, SimSettings};

fn scene() -> Scene {
    Scene::load(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/scenes/desk_box"),
    )
    .unwrap()
}

/// The rig with a tiny colour camera (only the probe matters) and the lamp held still.
fn rig(scene: &Scene) -> SimRig {
    let mut settings = SimSettings::placed_in(scene);
    settings.width = 16;
    settings.height = 12;
    settings.color_spp = 1;
    if let Some(lamp) = &mut settings.lamp {
        lamp.period_s = 1e9;
    }
    SimRig::new(scene, settings).unwrap().metered()
}

fn probe_frames(rig: &SimRig, frames: u32) -> Vec<Arc<Frame<ProbeImage>>> {
    (0..frames)
        .flat_map(|i| rig.frame(i).messages)
        .filter_map(|m| match m {
            StreamMessage::Probe(f) => Some(f),
            _ => None,
        })
        .collect()
}

#[test]
fn one_estimate_per_bracket_in_absolute_units() {
    let scene = scene();
    let rig = rig(&scene);
    let probe = rig.settings().probe.clone().unwrap();
    let bracket = probe.exposures_us.len();
    let frames = probe_frames(&rig, probe.every * (2 * bracket as u32) + 1);
    assert_eq!(frames.len(), 2 * bracket + 1);
    let mut lighting = ProbeLighting::new(&rig.calibration(), ProbeSettings::default()).unwrap();
    let mut estimates = Vec::new();
    for (i, frame) in frames.iter().enumerate() {
        if let Some(estimate) = lighting.push(frame).unwrap() {
            estimates.push((i, estimate));
        }
    }
    let at: Vec<usize> = estimates.iter().map(|(i, _)| *i).collect();
    // The cycle is known once its first exposure comes round again.
    assert_eq!(at, [bracket, 2 * bracket], "one estimate per full bracket");
    let (last, estimate) = &estimates[1];
    assert_eq!(estimate.stamp, frames[*last].stamp);
    assert_eq!(estimate.exposures, bracket);
    assert!(estimate.sh9.is_finite());

    // The strongest true light at the probe against the brightest median-cut light.
    let origin = rig.calibration().world_from_probe.translation;
    let (direction, irradiance) = rig
        .lights(0)
        .iter()
        .filter_map(|l| l.incident(origin))
        .map(|i| (i.direction_to_light, i.irradiance))
        .max_by(|a, b| a.1.max_element().total_cmp(&b.1.max_element()))
        .unwrap();
    let near: Vec<(Vec3, Vec3)> = estimate
        .lights
        .iter()
        .filter_map(|l| match l {
            relight_core::light::Light::Directional {
                direction_in_world,
                irradiance,
            } => Some((-*direction_in_world, *irradiance)),
            _ => None,
        })
        .filter(|(d, _)| d.angle_between(direction).to_degrees() < 6.0)
        .collect();
    let found: Vec3 = near.iter().map(|(_, e)| *e).sum();
    let mean = near
        .iter()
        .map(|(d, e)| *d * e.max_element())
        .sum::<Vec3>()
        .normalize();
    let angle = mean.angle_between(direction).to_degrees();
    let ratio = found / irradiance;
    eprintln!("strongest light: {angle:.2}° off, irradiance / truth = {ratio}");
    assert!(angle < 1.0, "{angle}°");
    // Absolute: the calibration's radiance scale undoes the probe's exposure scale.
    assert!((ratio - Vec3::ONE).abs().max_element() < 0.05, "{ratio}");
}

#[test]
fn a_single_exposure_or_a_size_change_is_no_bracket() {
    let scene = scene();
    let rig = rig(&scene);
    let frames = probe_frames(&rig, 40);
    let mut lighting = ProbeLighting::new(&rig.calibration(), ProbeSettings::default()).unwrap();
    // The same exposure again and again never completes a bracket.
    for _ in 0..3 {
        assert!(lighting.push(&frames[0]).unwrap().is_none());
    }
    // A frame of another size starts over: the old frames leave the bracket.
    let mut small = (*frames[1]).clone();
    small.payload.image = relight_core::Image::new(8, 8, relight_core::PixelFormat::Rgb8);
    assert!(lighting.push(&Arc::new(small)).unwrap().is_none());
    assert!(lighting.push(&frames[1]).unwrap().is_none());
}

#[test]
fn a_rig_without_a_fisheye_probe_is_refused() {
    let calibration = relight_core::rig::RigCalibration::default();
    assert!(ProbeLighting::new(&calibration, ProbeSettings::default()).is_err());
}
