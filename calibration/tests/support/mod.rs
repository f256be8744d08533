//! Shared by the intrinsics tests: detections of a target in synthetic views of known truth.

use std::time::Instant;

use relight_calibrate::detect::{Detection, Detector};
use relight_calibrate::synth::{RenderSettings, SynthCamera, ViewPlan, plan_views};
use relight_calibrate::target::TargetGeometry;
use relight_core::camera::CameraModel;

/// Renders `views` planned views of `geometry` through `model` and detects the target in each,
/// printing the corner RMS against the truth and the render/detect times.
pub fn detections(geometry: &TargetGeometry, model: CameraModel, views: usize) -> Vec<Detection> {
    let synth = SynthCamera::new(model, RenderSettings::default()).unwrap();
    let poses = plan_views(
        &model,
        geometry,
        &ViewPlan {
            count: views,
            ..ViewPlan::default()
        },
    );
    let detector = Detector::new(geometry).unwrap();
    let mut found = Vec::new();
    let mut corner_sq = 0.0;
    let mut corner_n = 0usize;
    let mut render_s = 0.0;
    let mut detect_s = 0.0;
    for (i, pose) in poses.iter().enumerate() {
        let t = Instant::now();
        let image = synth.render_target(geometry, pose);
        render_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let name = format!("view-{i:02}");
        let detection = detector.detect(&name, &image);
        detect_s += t.elapsed().as_secs_f64();
        let Ok(detection) = detection else {
            eprintln!("{name}: {detection:?}");
            continue;
        };
        for (id, p) in synth.visible_points(geometry, pose) {
            if let Some(q) = detection.pixel_of(id) {
                corner_sq += p.distance_squared(q);
                corner_n += 1;
            }
        }
        found.push(detection);
    }
    eprintln!(
        "{}: {} of {} views detected, corner RMS vs truth {:.4} px over {corner_n} corners; render {render_s:.2} s, detect {detect_s:.2} s",
        geometry.target().describe(),
        found.len(),
        views,
        (corner_sq / corner_n.max(1) as f64).sqrt()
    );
    found
}
