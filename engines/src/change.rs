//! What counts as a change of a picture's inputs, for what is kept over frames (`pt`'s running
//! means) and for the `auto` governor's still/moving state: how far the picture moved between
//! two camera poses, in pixels (a tracked camera's pose jitters by fractions of a millimetre
//! and a degree, so equality is the wrong test), and a key of the scene's content besides the
//! camera (a live depth surface by its revision, so sensor noise on a held surface is no
//! change).

use std::hash::{DefaultHasher, Hash, Hasher};

use glam::Vec3;
use relight_core::scene::{Scene, SceneCamera};

/// Image motion (pixels) under which the camera counts as still: what is kept over frames is
/// kept, and drawn from the held pose, so a tracked camera's jitter does not restart it.
pub const STILL_PX: f32 = 0.25;

/// A hash of what a picture of `scene` depends on besides the camera: the geometry (a live
/// depth surface by its [`Scene::surface_revision`]), the materials, the lights and the
/// environment map.
pub fn scene_key(scene: &Scene) -> u64 {
    let mut hasher = DefaultHasher::new();
    let floats = |v: &[Vec3], hasher: &mut DefaultHasher| {
        for p in v {
            p.to_array().map(f32::to_bits).hash(hasher);
        }
    };
    scene.surface_revision.hash(&mut hasher);
    for mesh in &scene.meshes {
        if scene.surface_revision.is_some() && !mesh.is_virtual {
            continue;
        }
        (mesh.is_virtual, mesh.material, &mesh.triangles).hash(&mut hasher);
        floats(&mesh.positions_in_world, &mut hasher);
        floats(&mesh.normals_in_world, &mut hasher);
        floats(&mesh.vertex_albedo, &mut hasher);
    }
    for m in &scene.materials {
        floats(&[m.albedo, m.specular, m.emission], &mut hasher);
        m.shininess.to_bits().hash(&mut hasher);
    }
    format!("{:?}", scene.lights).hash(&mut hasher);
    if let Some(env) = &scene.environment {
        (env.width, env.height).hash(&mut hasher);
        floats(&env.radiance, &mut hasher);
    }
    hasher.finish()
}

/// How far the picture moves, in pixels of an image `height_px` tall, when the camera moves
/// from `a` to `b`: the largest displacement of five points `depth_m` in front of `a`
/// reprojected into `b`, on its axis and halfway to the image's corners (the middle of the
/// picture, where the object is framed). A point behind `b`, or a change
/// of field of view (the picture is rescaled), is infinite motion.
///
/// Reprojected rather than bounded: a pose fitted to a marker board errs by a turn and a shift
/// that largely cancel where the board is (on a simulated tripod at 320 × 240, 3 mm and 0.08°
/// off the truth, yet the object's image 0.08 px off at the median); the sum of the two
/// (focal length × angle plus the shift seen at that depth) read 0.9 px from one frame to the
/// next there, this 0.21 px from the held pose.
pub fn image_shift_px(a: &SceneCamera, b: &SceneCamera, height_px: u32, depth_m: f32) -> f32 {
    if a.yfov_rad != b.yfov_rad {
        return f32::INFINITY;
    }
    let tan_half = (a.yfov_rad / 2.0).tan();
    let focal_px = height_px as f32 / (2.0 * tan_half);
    let aspect = if a.height > 0 {
        a.width as f32 / a.height as f32
    } else {
        1.0
    };
    let depth = depth_m.max(1e-3);
    let b_from_a = b.world_from_camera.inverse() * a.world_from_camera;
    let shift = [
        (0.0, 0.0),
        (-0.5, -0.5),
        (0.5, -0.5),
        (-0.5, 0.5),
        (0.5, 0.5),
    ]
    .into_iter()
    .map(|(u, v): (f32, f32)| {
        // Image plane at unit distance, cameras looking along −z.
        let in_a = Vec3::new(u * tan_half * aspect, v * tan_half, -1.0);
        let in_b = b_from_a.transform_point(in_a * depth);
        if in_b.z >= 0.0 {
            return f32::INFINITY;
        }
        let seen = in_b.truncate() / -in_b.z;
        focal_px * seen.distance(in_a.truncate())
    })
    .fold(0.0f32, f32::max);
    if shift.is_finite() {
        shift
    } else {
        f32::INFINITY
    }
}

/// The distance at which the relit content lies: from the camera to the centre of the virtual
/// object's box, or of the real scene's when there is no object; 1 m without either.
pub fn focus_depth_m(camera: &SceneCamera, focus: Option<(Vec3, Vec3)>) -> f32 {
    focus
        .map(|(lo, hi)| (lo + hi) / 2.0)
        .map(|centre| centre.distance(camera.world_from_camera.translation))
        .filter(|d| d.is_finite() && *d > 0.0)
        .unwrap_or(1.0)
}

/// [`focus_depth_m`] of `scene`'s camera at its virtual object, or at its real geometry when
/// it has none: where the picture's motion matters.
pub fn scene_focus_depth_m(scene: &Scene) -> f32 {
    focus_depth_m(
        &scene.camera,
        scene.virtual_bounds().or_else(|| scene.real_bounds()),
    )
}

/// Whether `scene`'s camera, `height_px` pixels tall, moves the picture by at most
/// [`STILL_PX`] from `held` at the scene's focus: a camera still enough to keep what was
/// accumulated from `held`.
pub fn camera_still(held: &SceneCamera, scene: &Scene, height_px: u32) -> bool {
    image_shift_px(held, &scene.camera, height_px, scene_focus_depth_m(scene)) <= STILL_PX
}

#[cfg(test)]
mod tests {
    use glam::Quat;
    use relight_core::Pose;

    use super::*;

    fn camera(translation: Vec3, turned_deg: f32) -> SceneCamera {
        SceneCamera {
            world_from_camera: Pose {
                rotation: Quat::from_rotation_y(turned_deg.to_radians()),
                translation,
            },
            yfov_rad: 60f32.to_radians(),
            width: 160,
            height: 120,
        }
    }

    #[test]
    fn a_turn_moves_the_picture_by_the_focal_length_times_the_angle() {
        let focal = 120.0 / (2.0 * 30f32.to_radians().tan());
        let angle = 0.1f32.to_radians();
        let shift = image_shift_px(&camera(Vec3::ZERO, 0.0), &camera(Vec3::ZERO, 0.1), 120, 1.0);
        // The axis moves by f·tan θ; a point (x, y) off it by f·θ·(1 + x²/f², x·y/f²), here
        // a quarter of the image's width and height off: 1.153 f·θ.
        assert!(
            shift >= focal * angle.tan() && shift <= 1.16 * focal * angle,
            "{shift} against {}",
            focal * angle
        );
        // A shift parallel to the image moves every point at that depth alike.
        let moved = image_shift_px(
            &camera(Vec3::ZERO, 0.0),
            &camera(Vec3::new(0.001, 0.0, 0.0), 0.0),
            120,
            2.0,
        );
        assert!((moved - focal * 0.0005).abs() < 1e-4, "{moved}");
        assert_eq!(
            image_shift_px(&camera(Vec3::ZERO, 0.0), &camera(Vec3::ZERO, 0.0), 120, 1.0),
            0.0
        );
        let mut zoomed = camera(Vec3::ZERO, 0.0);
        zoomed.yfov_rad *= 0.9;
        assert!(image_shift_px(&camera(Vec3::ZERO, 0.0), &zoomed, 120, 1.0).is_infinite());
        let turned_away = camera(Vec3::ZERO, 180.0);
        assert!(image_shift_px(&camera(Vec3::ZERO, 0.0), &turned_away, 120, 1.0).is_infinite());
    }

    /// A camera that turns about the point it looks at, as a pose fitted to a marker board errs
    /// (a turn and a shift that cancel at the board), barely moves the middle of the picture at
    /// that depth: 0.1° about a point 2 m away moves it by 0.14 px of a 104 px focal length
    /// (x²θ/4f with x a quarter of the width), where turn plus shift counted 0.36 px.
    #[test]
    fn a_turn_about_the_focus_barely_moves_it() {
        let focus = Vec3::new(0.0, 0.0, -2.0);
        let turn = Quat::from_rotation_y(0.1f32.to_radians());
        let orbited = SceneCamera {
            world_from_camera: Pose {
                rotation: turn,
                translation: focus + turn * -focus,
            },
            ..camera(Vec3::ZERO, 0.0)
        };
        let focal = 120.0 / (2.0 * 30f32.to_radians().tan());
        let shift = image_shift_px(&camera(Vec3::ZERO, 0.0), &orbited, 120, 2.0);
        let turn_plus_shift = 2.0 * focal * 0.1f32.to_radians();
        assert!(
            shift < 0.1 * turn_plus_shift,
            "{shift} against {turn_plus_shift}"
        );
    }
}
