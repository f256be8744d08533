//! Shared by the engine tests: scenes, frames, running an engine, the reference, error metrics.
#![allow(dead_code)]

use std::path::Path;
use std::sync::Arc;

use glam::Vec3;
use relight_core::scene::{EnvironmentMap, Scene};
use relight_core::{Frame, Image, PixelFormat, Timestamp};
use relight_engines::reference::{ReferenceImages, ReferenceSettings, render_reference};
use relight_engines::{Engine, EngineRegistry, RelitFrame, SceneFrame};

pub fn load_scene(name: &str) -> Scene {
    Scene::load(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../tests/scenes")
            .join(name),
    )
    .unwrap()
}

/// A frame of `scene` at `width` × `height` over a mid-grey background.
pub fn frame(scene: Arc<Scene>, width: u32, height: u32) -> SceneFrame {
    let mut color = Image::new(width, height, PixelFormat::Rgb8);
    if let Some(px) = color.as_u8_mut() {
        px.fill(128);
    }
    SceneFrame {
        stamp: Timestamp::new(0, 0),
        seq: 0,
        color: Some(Arc::new(Frame::new(0, Timestamp::new(0, 0), color))),
        depth: None,
        scene: Some(scene),
    }
}

pub fn engine(name: &str) -> Box<dyn Engine> {
    engine_with(name, serde_json::json!({}))
}

/// An engine with parameters, e.g. `json!({"steps": 8})`.
pub fn engine_with(name: &str, params: serde_json::Value) -> Box<dyn Engine> {
    let params = params.as_object().cloned().unwrap_or_default();
    EngineRegistry::new()
        .build(name, &params)
        .unwrap_or_else(|e| panic!("{e}"))
        .engine
}

/// Run `engine` on `frame`: Δ per pixel and the output.
pub fn delta_of(engine: &mut Box<dyn Engine>, frame: &SceneFrame) -> (Vec<Vec3>, RelitFrame) {
    let mut out = RelitFrame::default();
    engine
        .render(frame, &mut out)
        .unwrap_or_else(|e| panic!("{e}"));
    (relight_engines::offline::delta_pixels(&out.delta), out)
}

/// `engine` with `params` on `frame`: the object's error against `reference`
/// ([`relight_engines::offline::object_error`]) and Δ per pixel.
pub fn object_and_delta(
    engine: &str,
    params: serde_json::Value,
    frame: &SceneFrame,
    reference: &ReferenceImages,
) -> (f64, Vec<Vec3>) {
    let (delta, out) = delta_of(&mut engine_with(engine, params), frame);
    let object = relight_engines::offline::object_error(
        &out.composite,
        &reference.l_rho,
        &reference.virtual_mask,
    )
    .expect("the object is in view");
    (object, delta)
}

/// `engine` with `params` on `scene`, at `reference`'s size, judged against it: Δ L2 on real
/// pixels, the object's L2, and Δ per pixel.
pub fn errors_against(
    engine: &str,
    params: serde_json::Value,
    scene: &Arc<Scene>,
    reference: &ReferenceImages,
) -> (f64, f64, Vec<Vec3>) {
    let frame = frame(scene.clone(), reference.width, reference.height);
    let (object, delta) = object_and_delta(engine, params, &frame, reference);
    let (delta_l2, _) = relative_l2(&delta, &reference.delta, &reference.virtual_mask);
    (f64::from(delta_l2), object, delta)
}

/// `engine` with `setting = better` against `setting = worse` (each over `base`; a value that
/// parses as a number is passed as one), on each of
/// `cases`' scenes at 80 × 60 against a `spp` reference: Δ L2 on real pixels with `better`
/// must be under `gain` × that with `worse`.
pub fn setting_brings_delta_closer(
    engine: &str,
    base: serde_json::Value,
    (setting, better, worse): (&str, &str, &str),
    cases: &[(&str, f64)],
    spp: u32,
) {
    for &(name, gain) in cases {
        let scene = Arc::new(load_scene(name));
        let reference = reference_full(&scene, 80, 60, spp);
        let error = |value: &str| {
            let mut params = base.as_object().cloned().unwrap_or_default();
            let value = match (value.parse::<i64>(), value.parse::<f64>()) {
                (Ok(int), _) => int.into(),
                (_, Ok(float)) => float.into(),
                _ => value.into(),
            };
            params.insert(setting.into(), value);
            errors_against(
                engine,
                serde_json::Value::Object(params),
                &scene,
                &reference,
            )
            .0
        };
        let (with, without) = (error(better), error(worse));
        eprintln!(
            "{engine} on {name}: Δ {with:.4} with {setting} = {better}, {without:.4} with {worse}"
        );
        assert!(
            with < gain * without,
            "{engine} on {name}: Δ {with} with {setting} = {better}, {without} with {worse}"
        );
    }
}

/// `engine` on touching_wall (a box in the corner of a floor and a wall), at 80 × 60 against
/// 256 spp, with its volume moved into the scene (`volume_placement = scene`, the default)
/// and centred on the object: moved, both Δ on real pixels and the object come closer to the
/// reference, the object by at least `object_gain` (error ratio). `base`: the engine's other
/// parameters. Returns (Δ, object) moved, then centred.
pub fn the_volume_in_the_scene_beats_the_centred_one(
    engine: &str,
    base: serde_json::Value,
    object_gain: f64,
) -> ((f64, f64), (f64, f64)) {
    let scene = Arc::new(load_scene("touching_wall"));
    let reference = reference_full(&scene, 80, 60, 256);
    let errors = |placement: &str| {
        let mut params = base.as_object().cloned().unwrap_or_default();
        params.insert("volume_placement".into(), placement.into());
        let (delta, object, _) = errors_against(
            engine,
            serde_json::Value::Object(params),
            &scene,
            &reference,
        );
        (delta, object)
    };
    let (moved, centred) = (errors("scene"), errors("centred"));
    eprintln!(
        "{engine} on touching_wall, Δ / object: {:.4} / {:.4} moved, {:.4} / {:.4} centred",
        moved.0, moved.1, centred.0, centred.1
    );
    assert!(moved.0 < centred.0, "Δ {moved:?} against {centred:?}");
    assert!(
        moved.1 < object_gain * centred.1,
        "object {moved:?} against {centred:?}"
    );
    (moved, centred)
}

/// A setting that lights the object with the room's bounce light (`far_field` of the volume
/// engines, `environment` of `ibl`): on `scenes`, whose object sees much of it (desk_box's walls
/// and floor, touching_wall's wall, window_env's floor), `engine` with `setting = on` must draw
/// the object's pixels closer to the full reference than with `off`, by at least `gain` (error
/// ratio), and leave every real pixel's Δ as it is (the setting lights the object alone).
/// Returns (scene, with, without) per scene.
pub fn setting_brings_the_object_closer(
    engine: &str,
    setting: (&str, &str, &str),
    scenes: &[&'static str],
    gain: f64,
) -> Vec<(&'static str, f64, f64)> {
    setting_brings_the_object_closer_with(engine, &[], setting, scenes, gain)
}

/// [`setting_brings_the_object_closer`] with `base` parameters set in both renders.
pub fn setting_brings_the_object_closer_with(
    engine: &str,
    base: &[(&str, &str)],
    (setting, on, off): (&str, &str, &str),
    scenes: &[&'static str],
    gain: f64,
) -> Vec<(&'static str, f64, f64)> {
    let mut errors = Vec::new();
    for &name in scenes {
        let scene = Arc::new(load_scene(name));
        let (w, h) = (80, 60);
        let reference = reference_full(&scene, w, h, 64);
        let render = |value: &str| {
            let mut params: serde_json::Map<String, serde_json::Value> = base
                .iter()
                .map(|(k, v)| (k.to_string(), serde_json::json!(v)))
                .collect();
            params.insert(setting.into(), serde_json::json!(value));
            object_and_delta(
                engine,
                serde_json::Value::Object(params),
                &frame(scene.clone(), w, h),
                &reference,
            )
        };
        let ((with, delta_with), (without, delta_without)) = (render(on), render(off));
        eprintln!(
            "{engine} on {name}: object {with:.4} with {setting} = {on}, {without:.4} with {off}"
        );
        assert!(
            with < gain * without,
            "{engine} on {name}: object {with} with {setting} = {on}, {without} with {off}"
        );
        let real = |delta: &[Vec3]| -> Vec<Vec3> {
            delta
                .iter()
                .zip(&reference.virtual_mask)
                .filter(|(_, on_object)| !**on_object)
                .map(|(d, _)| *d)
                .collect()
        };
        assert_eq!(
            real(&delta_with),
            real(&delta_without),
            "{engine} on {name}: Δ on real pixels"
        );
        errors.push((name, with, without));
    }
    errors
}

/// window_env, lit by its map alone, rendered by `engine` with its default `env_lights` and with
/// 8 (the count every engine used before the parameter), each judged against the full
/// reference at 80 × 60: with the default, Δ L2 on real pixels and the object's L2 must both be
/// under 0.9 × their values with 8. More lights share the window's light more finely, so its
/// shadows soften as the reference's do and the far field gathers a smoother floor.
pub fn more_environment_lights_bring_window_env_closer(engine: &str) {
    let scene = Arc::new(load_scene("window_env"));
    let reference = reference_full(&scene, 80, 60, 64);
    let errors = |params| errors_against(engine, params, &scene, &reference);
    let (delta, object, _) = errors(serde_json::json!({}));
    let (delta_8, object_8, _) = errors(serde_json::json!({ "env_lights": 8 }));
    eprintln!(
        "{engine} on window_env, Δ / object: {delta:.4} / {object:.4} by default, \
         {delta_8:.4} / {object_8:.4} with 8 lights"
    );
    assert!(
        delta < 0.9 * delta_8,
        "{engine}: Δ L2 {delta} against {delta_8}"
    );
    assert!(
        object < 0.9 * object_8,
        "{engine}: object L2 {object} against {object_8}"
    );
}

/// window_env's environment lights are all directional, so `engine`'s VPL maps are thinned
/// (`MapSizes::for_faces`: 24 faces at half the edge, 16 at 0.61 of it, rounded down to a
/// multiple of 8). Against the same engine with `rsm_size` doubled (finer maps than before
/// the thinning), at 80 × 60 against 64 spp: Δ and the object's error within 5 % (the bench at
/// 160 × 120: within 0.002 of the unthinned maps), and the pictures differ.
pub fn thinner_maps_for_an_environment_keep_the_error(engine: &str, rsm_size: u32) {
    let scene = Arc::new(load_scene("window_env"));
    let reference = reference_full(&scene, 80, 60, 64);
    let errors = |params| errors_against(engine, params, &scene, &reference);
    let (delta_l2, object, delta) = errors(serde_json::json!({}));
    let (delta_l2_full, object_full, delta_full) =
        errors(serde_json::json!({ "rsm_size": 2 * rsm_size }));
    eprintln!(
        "{engine} on window_env, Δ / object: {delta_l2:.4} / {object:.4} by default, \
         {delta_l2_full:.4} / {object_full:.4} with the maps at full edge"
    );
    assert!(
        delta_l2 < 1.05 * delta_l2_full,
        "Δ {delta_l2} against {delta_l2_full}"
    );
    assert!(
        object < 1.05 * object_full,
        "object {object} against {object_full}"
    );
    assert_ne!(delta, delta_full, "the maps were not thinned");
}

/// `engine` gathers at every second pixel per axis by default (`param` 2), the pixels between
/// taking their alike neighbours' irradiance (`engines/src/strided.rs`). On desk_box, whose
/// object stands on the desk against the wall (silhouettes and depth edges where no neighbour is
/// alike), at the bench's 160 × 120 against 128 spp: Δ and the object's error are no more than
/// 0.01 above gathering every pixel, and the pictures differ (the stride is in effect).
pub fn a_stride_of_two_keeps_the_error(engine: &str, param: &str) {
    let scene = Arc::new(load_scene("desk_box"));
    let reference = reference_full(&scene, 160, 120, 128);
    let errors = |params| errors_against(engine, params, &scene, &reference);
    let (delta_l2, object, delta) = errors(serde_json::json!({}));
    let (delta_l2_1, object_1, delta_1) = errors(serde_json::json!({ param: 1 }));
    eprintln!(
        "{engine} on desk_box, Δ / object: {delta_l2:.4} / {object:.4} by default, \
         {delta_l2_1:.4} / {object_1:.4} with {param} 1"
    );
    assert!(
        delta_l2 < delta_l2_1 + 0.01,
        "Δ {delta_l2} against {delta_l2_1}"
    );
    assert!(
        object < object_1 + 0.01,
        "object {object} against {object_1}"
    );
    assert_ne!(delta, delta_1, "{param} 2 changed nothing");
}

/// `engine`'s defaults on `scene` against `before`, the settings it had until stop 43, at 80 × 60
/// against 256 spp: Δ on real pixels and the object's error must both be under 0.95 × theirs;
/// and its VPL maps at their default size (`rsm_size`) within 3 % of what 256² gives.
pub fn the_defaults_beat(engine: &str, scene: &'static str, before: serde_json::Value) {
    let scene_arc = Arc::new(load_scene(scene));
    let reference = reference_full(&scene_arc, 80, 60, 256);
    let errors = |params| {
        let (delta, object, _) = errors_against(engine, params, &scene_arc, &reference);
        (delta, object)
    };
    let (delta, object) = errors(serde_json::json!({}));
    let (delta_before, object_before) = errors(before);
    let (delta_256, object_256) = errors(serde_json::json!({ "rsm_size": 256 }));
    eprintln!(
        "{engine} on {scene}, Δ / object: {delta:.4} / {object:.4} by default, \
         {delta_before:.4} / {object_before:.4} before, {delta_256:.4} / {object_256:.4} with \
         256² VPL maps"
    );
    assert!(
        delta < 0.95 * delta_before,
        "Δ {delta} against {delta_before}"
    );
    assert!(
        object < 0.95 * object_before,
        "object {object} against {object_before}"
    );
    assert!(
        (delta / delta_256 - 1.0).abs() < 0.03,
        "Δ {delta} against {delta_256}"
    );
    assert!(
        (object / object_256 - 1.0).abs() < 0.03,
        "object {object} against {object_256}"
    );
}

/// Half the edge of [`object_over_a_floor`]'s floor (m).
pub const FLOOR_HALF_EDGE: f32 = 4.0;
/// The material of [`object_over_a_floor`]'s floor: desk_box's white.
pub const FLOOR_MATERIAL: usize = 0;

/// desk_box's object alone, `gap` × its largest edge above a white floor 8 m square centred
/// under it, lit from straight above by a directional light of unit irradiance, without an
/// environment: the object's vertical faces get no direct light, only the floor's bounce.
pub fn object_over_a_floor(gap: f32) -> Scene {
    let mut scene = load_scene("desk_box");
    let (lo, hi) = scene.virtual_bounds().expect("desk_box has an object");
    let centre = (lo + hi) / 2.0;
    let floor_y = lo.y - gap * (hi - lo).max_element();
    let half = FLOOR_HALF_EDGE;
    scene.meshes.retain(|m| m.is_virtual);
    let corner = |dx: f32, dz: f32| Vec3::new(centre.x + dx, floor_y, centre.z + dz);
    scene.meshes.push(relight_core::scene::Mesh {
        name: "floor".into(),
        positions_in_world: vec![
            corner(-half, -half),
            corner(half, -half),
            corner(half, half),
            corner(-half, half),
        ],
        normals_in_world: vec![Vec3::Y; 4],
        triangles: vec![[0, 2, 1], [0, 3, 2]],
        material: FLOOR_MATERIAL,
        is_virtual: false,
        vertex_albedo: Vec::new(),
    });
    scene.lights = vec![relight_core::light::Light::Directional {
        direction_in_world: Vec3::NEG_Y,
        irradiance: Vec3::ONE,
    }];
    scene.environment = None;
    scene
}

/// The far field against an analytic value: desk_box's object alone over a white floor 8 m
/// square, far enough below that none of it falls in the volume, lit from straight above by a
/// directional light. Only the floor's bounce light reaches the object's vertical faces, and all
/// of it through the far field, so `far_field = "probe"` minus `"none"` on the front face (normal
/// +z) must be the box's albedo/π times the floor's irradiance at the volume's centre,
/// ∫ L_floor ⟨n, ω⟩₊ cos θ_floor / r² dA (integrated here on a fine grid): the mean over the
/// face's pixels within 10 % of it.
pub fn the_far_field_of_a_floor_matches_its_integral(engine: &str) {
    let gap = 3.0;
    let scene = object_over_a_floor(gap);
    let (lo, hi) = scene.virtual_bounds().expect("desk_box has an object");
    let centre = (lo + hi) / 2.0;
    let floor_y = lo.y - gap * (hi - lo).max_element();
    let half = FLOOR_HALF_EDGE;
    let (white, irradiance) = (FLOOR_MATERIAL, 1.0f32);
    let box_albedo = {
        let object = scene.meshes.iter().find(|m| m.is_virtual).expect("the box");
        f64::from(scene.materials[object.material].albedo.x)
    };
    let floor_radiance =
        f64::from(scene.materials[white].albedo.x * irradiance) / std::f64::consts::PI;
    // ∫ over the floor, n = +z, at the centre.
    let steps = 800;
    let cell = 2.0 * f64::from(half) / f64::from(steps);
    let height = f64::from(centre.y - floor_y);
    let mut expected_irradiance = 0.0;
    for i in 0..steps {
        for j in 0..steps {
            let x = -f64::from(half) + (f64::from(i) + 0.5) * cell;
            let z = -f64::from(half) + (f64::from(j) + 0.5) * cell;
            let r2 = x * x + z * z + height * height;
            let cos_face = (z / r2.sqrt()).max(0.0);
            let cos_floor = height / r2.sqrt();
            expected_irradiance += floor_radiance * cos_face * cos_floor / r2 * cell * cell;
        }
    }
    let expected = box_albedo / std::f64::consts::PI * expected_irradiance;

    let scene = Arc::new(scene);
    let (w, h) = (160, 120);
    let render = |far_field| {
        delta_of(
            &mut engine_with(
                engine,
                serde_json::json!({ "far_field": far_field, "accumulate": 1 }),
            ),
            &frame(scene.clone(), w, h),
        )
        .0
    };
    let (with, without) = (render("probe"), render("none"));
    // The object's pixels are the ones the far field changes; its front face gets most (the
    // top faces away from the floor).
    let added: Vec<f64> = with
        .iter()
        .zip(&without)
        .map(|(a, b)| f64::from(a.x - b.x))
        .filter(|d| *d > 0.5 * expected)
        .collect();
    assert!(
        added.len() > 50,
        "{engine}: {} front-face pixels",
        added.len()
    );
    let measured = added.iter().sum::<f64>() / added.len() as f64;
    eprintln!(
        "{engine}: far field on the front face {measured:.5} over {} pixels, expected {expected:.5}",
        added.len()
    );
    assert!(
        (measured / expected - 1.0).abs() < 0.1,
        "{engine}: measured {measured}, expected {expected}"
    );
}

/// The reference with direct light only (no bounce after the first hit), sampling pixel
/// centres as the engines' rasteriser does (so silhouettes agree pixel for pixel).
pub fn reference_direct(scene: &Scene, width: u32, height: u32, spp: u32) -> ReferenceImages {
    render_reference(
        scene,
        ReferenceSettings {
            spp,
            max_bounces: 0,
            pixel_jitter: false,
            size: Some((width, height)),
            ..ReferenceSettings::default()
        },
    )
    .unwrap()
}

/// The full reference (all bounces), pixel centres: what the bench judges by.
pub fn reference_full(scene: &Scene, width: u32, height: u32, spp: u32) -> ReferenceImages {
    relight_engines::offline::reference(scene, width, height, spp).unwrap()
}

/// ‖Δ − Δ_ref‖ / ‖Δ_ref‖ over real pixels (the bench's metric), and ‖Δ_ref‖ itself.
pub fn relative_l2(delta: &[Vec3], reference: &[Vec3], virtual_mask: &[bool]) -> (f32, f32) {
    let (error, _) = relight_engines::offline::delta_error(delta, reference, virtual_mask);
    (error as f32, real_norm(reference, virtual_mask) as f32)
}

/// ‖v‖₂ over the real pixels (where `virtual_mask` is false).
pub fn real_norm(values: &[Vec3], virtual_mask: &[bool]) -> f64 {
    values
        .iter()
        .zip(virtual_mask)
        .filter(|(_, v)| !**v)
        .map(|(v, _)| f64::from(v.length_squared()))
        .sum::<f64>()
        .sqrt()
}

/// Pixels whose 8-neighbourhood in `delta` spans more than `fraction` of the image's largest
/// |Δ|: where a shadow or silhouette boundary passes.
pub fn edge_pixels(delta: &[Vec3], width: usize, height: usize, fraction: f32) -> Vec<bool> {
    let scale = delta
        .iter()
        .map(|d| d.abs().max_element())
        .fold(0.0, f32::max);
    let threshold = fraction * scale;
    (0..delta.len())
        .map(|i| {
            let (x, y) = (i % width, i / width);
            let mut lo = Vec3::splat(f32::INFINITY);
            let mut hi = Vec3::splat(f32::NEG_INFINITY);
            for ny in y.saturating_sub(1)..=(y + 1).min(height - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(width - 1) {
                    let d = delta[ny * width + nx];
                    lo = lo.min(d);
                    hi = hi.max(d);
                }
            }
            (hi - lo).max_element() > threshold
        })
        .collect()
}

/// Largest |Δ| over every pixel and channel.
pub fn max_abs(delta: &[Vec3]) -> f32 {
    delta
        .iter()
        .map(|d| d.abs().max_element())
        .fold(0.0, f32::max)
}

/// A sun-like spot in `env`: texel (`x`, `y`) set to `ratio` times the map's brightest texel.
pub fn add_sun(env: &mut EnvironmentMap, x: usize, y: usize, ratio: f32) {
    let peak = env
        .radiance
        .iter()
        .map(|l| l.max_element())
        .fold(0.0, f32::max);
    env.radiance[y * env.width as usize + x] = Vec3::splat(peak * ratio);
}

/// `scene` with its virtual object(s) moved 50 m away along +x, far from everything visible.
pub fn virtual_moved_far_away(mut scene: Scene) -> Scene {
    for mesh in scene.meshes.iter_mut().filter(|m| m.is_virtual) {
        for p in &mut mesh.positions_in_world {
            p.x += 50.0;
        }
    }
    scene
}

/// [`object_over_a_floor`] at `gap`: the object's vertical faces take only the floor's bounce,
/// which near the floor comes through the volume and farther off through the far field. The
/// mean over those faces' pixels of `engine`'s composite (linear) over the reference's
/// L^ρ at one bounce (160 × 120, 64 spp, pixel centres).
pub fn unlit_faces_over_a_floor(engine: &str, params: serde_json::Value, gap: f32) -> f64 {
    let scene = Arc::new(object_over_a_floor(gap));
    let (w, h) = (160, 120);
    let reference = render_reference(
        &scene,
        ReferenceSettings {
            spp: 64,
            max_bounces: 1,
            pixel_jitter: false,
            size: Some((w, h)),
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    let direct = reference_direct(&scene, w, h, 1);
    let mut params = params;
    params["accumulate"] = 1.into();
    let (_, out) = delta_of(
        &mut engine_with(engine, params),
        &frame(scene.clone(), w, h),
    );
    let composite = relight_engines::offline::composite_pixels(&out.composite);
    assert_eq!(composite.len(), (w * h) as usize, "an 8-bit composite");
    let (mut engine_sum, mut reference_sum, mut pixels) = (0.0, 0.0, 0);
    for (((shown, truth), on_object), direct) in composite
        .iter()
        .zip(&reference.l_rho)
        .zip(&reference.virtual_mask)
        .zip(&direct.l_rho)
    {
        if *on_object && direct.y == 0.0 {
            engine_sum += f64::from(shown.y);
            reference_sum += f64::from(truth.y);
            pixels += 1;
        }
    }
    assert!(pixels > 40, "{pixels} unlit pixels");
    engine_sum / reference_sum
}
