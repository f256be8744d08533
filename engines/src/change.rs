//! What counts as a change of a picture's inputs, for what is kept over frames (`pt`'s running
//! means) and for the `auto` governor's still/moving state: how far the picture moved between
//! two camera poses, in pixels (a tracked camera's pose jitters by fractions of a millimetre
//! and a degree, so equality is the wrong test), and a key of the scene's content besides the
//! camera (a live depth surface by its revision, so sensor noise on a held surface is no
//! change).

use std::hash::{DefaultHasher, Hash, Hasher};

use glam::Vec3;
use relight_core::scene::{Scene, SceneCamera};

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

/// Upper bound of the image motion, in pixels of an image `height_px` tall, of a point
/// `depth_m` in front of the camera when the camera moves from `a` to `b`: the rotation
/// between them times the focal length, plus the translation as seen at that depth. A change
/// of field of view counts as motion too (the picture is rescaled).
pub fn image_shift_px(a: &SceneCamera, b: &SceneCamera, height_px: u32, depth_m: f32) -> f32 {
    if a.yfov_rad != b.yfov_rad {
        return f32::INFINITY;
    }
    let (pa, pb) = (a.world_from_camera, b.world_from_camera);
    let focal_px = height_px as f32 / (2.0 * (a.yfov_rad / 2.0).tan());
    // Quat::angle_between goes through acos, which loses small angles in f32.
    let relative = pa.rotation.inverse() * pb.rotation;
    let turned_rad = 2.0 * relative.xyz().length().atan2(relative.w.abs());
    let moved_m = pa.translation.distance(pb.translation);
    let shift = focal_px * (turned_rad + moved_m / depth_m.max(1e-3));
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
        let shift = image_shift_px(&camera(Vec3::ZERO, 0.0), &camera(Vec3::ZERO, 0.1), 120, 1.0);
        assert!(
            (shift - focal * 0.1f32.to_radians()).abs() < 1e-3,
            "{shift}"
        );
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
    }
}
