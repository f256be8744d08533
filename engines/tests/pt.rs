//! `pt`: progressive differential path tracing on the GPU.

mod support;

use std::sync::Arc;

use relight_engines::gpu::GpuContext;
use relight_engines::pt::Pt;
use relight_engines::{Engine, RelitFrame};
use support::*;

#[test]
fn scratch_match() {
    let ctx = Arc::new(GpuContext::new().unwrap());
    for name in [
        "desk_box",
        "glossy_floor",
        "spot_bleed",
        "touching_wall",
        "window_env",
    ] {
        let scene = Arc::new(load_scene(name));
        let (w, h) = (32, 24);
        let frame = frame(scene.clone(), w, h);
        let mut pt = Pt::new(ctx.clone()).unwrap();
        let mut params = Pt::schema().defaults();
        params.insert("spp".into(), 256.into());
        pt.set_params(&params);
        let mut out = RelitFrame::default();
        pt.render(&frame, &mut out).unwrap();
        let stats = pt.statistics().unwrap();
        let reference = relight_engines::reference::render_reference(
            &scene,
            relight_engines::reference::ReferenceSettings {
                spp: 256,
                size: Some((w, h)),
                ..Default::default()
            },
        )
        .unwrap();
        let sum = |v: &[glam::Vec3]| v.iter().fold(glam::DVec3::ZERO, |a, b| a + b.as_dvec3());
        let var = |v: &[glam::Vec3]| {
            v.iter()
                .fold(glam::DVec3::ZERO, |a, b| a + (*b * *b).as_dvec3())
        };
        let (a, b) = (sum(&stats.delta), sum(&reference.delta));
        let sigma = (var(&stats.delta_std_error) + var(&reference.delta_std_error)).map(f64::sqrt);
        let mut outliers = 0;
        for i in 0..stats.delta.len() {
            let d = (stats.delta[i] - reference.delta[i]).abs();
            let s = (stats.delta_std_error[i] * stats.delta_std_error[i]
                + reference.delta_std_error[i] * reference.delta_std_error[i])
                .map(f32::sqrt);
            if d.cmpgt(s * 4.0).any() {
                outliers += 1;
            }
        }
        eprintln!(
            "{name}: pt {a:.4} ref {b:.4} σ {sigma:.4} z {:.2} outliers {outliers}/{} est {:?}",
            (a - b) / sigma,
            stats.delta.len(),
            out.estimated_relative_error
        );
    }
}
