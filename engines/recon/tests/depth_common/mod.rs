//! Shared by the depth and albedo tests: simulated frames of the test scenes with their ground
//! truth, and the error measures the reports quote.
#![allow(dead_code)]

use std::path::Path;

use glam::Vec3;
use relight_core::camera::Pinhole;
use relight_core::light::Light;
use relight_core::recording::truth::{TruthKind, TruthMessage};
use relight_core::scene::Scene;
use relight_core::{Image, Pose, StreamMessage};
use relight_recon::depth::{DepthMap, GuidedFilterSettings, is_valid_depth};
use relight_recon::temporal::TemporalSettings;
use relight_sim::rig::{SimRig, SimSettings};
use relight_sim::trajectory::Trajectory;

pub fn load_scene(name: &str) -> Scene {
    Scene::load(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/scenes")
            .join(name),
    )
    .unwrap()
}

/// The small rig every test uses: 160 × 120, 4 spp colour, metered exposure, the lamp of
/// `placed_in`, no probe or marker board (the board's print would change the albedo).
pub fn rig(scene: &Scene, trajectory: Option<Trajectory>, frames: u32) -> SimRig {
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

/// One simulated frame and its truth.
pub struct SimData {
    pub depth: Image,
    pub color: Image,
    pub truth_depth: Vec<f32>,
    /// World frame, facing the camera; `None` where no surface.
    pub truth_normals: Vec<Option<Vec3>>,
    pub truth_albedo: Vec<Vec3>,
    pub truth_specular: Vec<f32>,
    pub world_from_camera: Pose,
    pub lights: Vec<Light>,
}

pub fn f16_to_f32(bits: u16) -> f32 {
    let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exponent = i32::from((bits >> 10) & 0x1f);
    let mantissa = f32::from(bits & 0x3ff);
    match exponent {
        0 => sign * mantissa * 2f32.powi(-24),
        31 if mantissa == 0.0 => sign * f32::INFINITY,
        31 => f32::NAN,
        e => sign * (1.0 + mantissa / 1024.0) * 2f32.powi(e - 15),
    }
}

fn rgba(image: &Image) -> Vec<[f32; 4]> {
    image
        .as_u16()
        .unwrap()
        .chunks_exact(4)
        .map(|c| [c[0], c[1], c[2], c[3]].map(f16_to_f32))
        .collect()
}

pub fn sim_data(rig: &SimRig, i: u32) -> SimData {
    let frame = rig.frame(i);
    let mut depth = None;
    let mut color = None;
    for message in &frame.messages {
        match message {
            StreamMessage::Depth(f) => depth = Some(f.payload.clone()),
            StreamMessage::Color(f) => color = Some(f.payload.clone()),
            _ => {}
        }
    }
    let mut truth_depth = Vec::new();
    let mut truth_normals = Vec::new();
    let mut truth_albedo = Vec::new();
    let mut truth_specular = Vec::new();
    for truth in frame.truth {
        match truth {
            TruthMessage::Image(TruthKind::Depth, f) => {
                truth_depth = f.payload.as_f32().unwrap().to_vec()
            }
            TruthMessage::Image(TruthKind::Normals, f) => {
                truth_normals = rgba(&f.payload)
                    .into_iter()
                    .map(|[x, y, z, a]| (a > 0.5).then(|| Vec3::new(x, y, z).normalize()))
                    .collect();
            }
            TruthMessage::Image(TruthKind::Albedo, f) => {
                for [r, g, b, s] in rgba(&f.payload) {
                    truth_albedo.push(Vec3::new(r, g, b));
                    truth_specular.push(s);
                }
            }
            _ => {}
        }
    }
    SimData {
        depth: depth.unwrap(),
        color: color.unwrap(),
        truth_depth,
        truth_normals,
        truth_albedo,
        truth_specular,
        world_from_camera: rig.world_from_camera(i),
        lights: rig.lights(i),
    }
}

pub fn filter_settings(camera: &Pinhole) -> GuidedFilterSettings {
    GuidedFilterSettings::kinect_v1(camera.fx as f32)
}

pub fn temporal_settings(camera: &Pinhole) -> TemporalSettings {
    TemporalSettings::kinect_v1(camera.fx as f32)
}

/// RMSE (m) of `depth` against the truth over `mask` pixels, and how many there were.
pub fn rmse(depth: &DepthMap, truth: &[f32], mask: &[bool]) -> (f32, usize) {
    let mut sum = 0.0f64;
    let mut n = 0;
    for ((z, t), m) in depth.metres.iter().zip(truth).zip(mask) {
        if *m {
            assert!(is_valid_depth(*z), "every compared pixel has depth");
            sum += f64::from(z - t).powi(2);
            n += 1;
        }
    }
    (((sum / n.max(1) as f64).sqrt()) as f32, n)
}

/// Mean and median of a list (NaN-free).
pub fn mean_median(mut values: Vec<f32>) -> (f32, f32) {
    if values.is_empty() {
        return (f32::NAN, f32::NAN);
    }
    values.sort_by(f32::total_cmp);
    let mean = values.iter().sum::<f32>() / values.len() as f32;
    (mean, values[values.len() / 2])
}

/// Everything the reconstruction produces for one frame.
pub struct Reconstructed {
    pub raw: DepthMap,
    pub filtered: DepthMap,
    pub merged: DepthMap,
    pub positions: relight_recon::normals::PositionMap,
    pub normals: relight_recon::normals::NormalMap,
}

/// Raw depth → guided filter → temporal merge → positions → normals, with the defaults.
pub fn reconstruct(
    data: &SimData,
    camera: &Pinhole,
    merge: &mut relight_recon::temporal::TemporalMerge,
) -> Reconstructed {
    use relight_recon::depth::{DepthRange, guided_filter};
    use relight_recon::normals::{NormalSettings, normals, positions};
    let raw = DepthMap::from_image(&data.depth, DepthRange::default()).unwrap();
    let filtered = guided_filter(&raw, &data.color, &filter_settings(camera)).unwrap();
    let merged = merge
        .merge(&filtered, camera, &data.world_from_camera)
        .unwrap();
    let positions = positions(&merged, camera).unwrap();
    let normals = normals(&positions, &NormalSettings::default());
    Reconstructed {
        raw,
        filtered,
        merged,
        positions,
        normals,
    }
}
