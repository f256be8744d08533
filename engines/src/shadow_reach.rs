//! The camera pixels on which the virtual object can change a real pixel's direct light: the
//! only pixels an engine with no indirect term on real pixels (`differential`, `ibl`) needs the
//! real scene's G-buffer for.
//!
//! The shading pass culls a real point `p`'s shadow-map lookups where the segment from `p` to a
//! light misses the object's bounds grown by one shadow-map texel (`may_shadow` in
//! `shaders/shade.wgsl`): there both maps hold the same depth, and Δ's direct term is exactly 0.
//! For a point or spot light at `L`, the points that pass the test are
//! C = {L + t (b − L) : b in the grown box, t ≥ 1}, the box and its shadow cone behind it, which
//! is convex; for a directional light, the box swept along the light's direction. Every real
//! point lies in the real meshes' bounds `A`, so the pixels that may hold a nonzero Δ lie in the
//! camera's projection of C ∩ A for some light, or of the object itself (whose own pixels read
//! the μ G-buffer behind it). [`reach_rect`] bounds that projection by a pixel rectangle; the
//! μ G-buffer's real meshes are rasterised inside it alone (a scissor, and only the triangles
//! [`triangles_within`] keeps), the shading passes run over it alone, and every pixel outside it
//! shows the camera's own picture with Δ = 0: exactly what the full passes computed there (the
//! tests below, bit for bit).
//!
//! The bound is conservative at each step: C truncated where it leaves A (the far end of the
//! cone at the distance of A's farthest corner from the light), its axis-aligned box
//! intersected with A's, that box's corners projected after clipping at the camera's near
//! plane, and the rectangle grown by a pixel. On the live depth mesh the G-buffer was bound by
//! its triangles (about 38 000), which llvmpipe drops at setup when they fall outside the
//! scissor.

use glam::{Mat4, Vec3, Vec4, Vec4Swizzles};
use relight_core::PixelRect;
use relight_core::scene::box_corners;

use crate::gpu_scene::{GpuFace, GpuLight};

/// `KIND_DIRECTIONAL` in `shaders/common.wgsl`.
const KIND_DIRECTIONAL: u32 = 2;

/// The pixels of a `width` × `height` image drawn with `view_proj` where the object (bounds
/// `object`) can change a real point's direct light from any of `lights` (shadow maps of
/// `shadow_size`² texels per face), the real points lying in `real` (bounds), or where a point
/// of one of the boxes `also` (an engine's indirect term's reach) may be seen.
pub fn reach_rect(
    view_proj: Mat4,
    (width, height): (u32, u32),
    lights: &[GpuLight],
    faces: &[GpuFace],
    shadow_size: u32,
    (object, also): ((Vec3, Vec3), &[(Vec3, Vec3)]),
    real: (Vec3, Vec3),
) -> PixelRect {
    let mut boxes = vec![object];
    boxes.extend_from_slice(also);
    for light in lights {
        let grown = grown_object(light, faces, shadow_size, object);
        match reach_bounds(light, grown, real) {
            Reach::Everywhere => return PixelRect::full(width, height),
            Reach::Within(b) => boxes.push(b),
            Reach::Nowhere => {}
        }
    }
    screen_rect(view_proj, (width, height), &boxes)
}

/// Where a light's reach, C ∩ A, lies.
enum Reach {
    /// The light is inside the grown object: every point may be shadowed.
    Everywhere,
    Within((Vec3, Vec3)),
    Nowhere,
}

/// The object's bounds grown by one shadow-map texel at its far side from the light, as
/// `may_shadow` grows them (`texel_footprint`), and a little more for rounding.
fn grown_object(
    light: &GpuLight,
    faces: &[GpuFace],
    shadow_size: u32,
    (lo, hi): (Vec3, Vec3),
) -> (Vec3, Vec3) {
    let Some(face) = faces.get(light.faces[0] as usize) else {
        return (lo, hi);
    };
    let size = shadow_size.max(1) as f32;
    let footprint = if face.light[1] == crate::gpu_scene::FACE_ORTHOGRAPHIC {
        face.axis[3].sqrt() / size
    } else {
        let at = Vec4::from(light.position).xyz();
        let farthest = (hi - at).abs().max((lo - at).abs()).length();
        2.0 * face.axis[3] * farthest / size
    };
    let grow = Vec3::splat(footprint * 1.01 + 1e-5 * (1.0 + lo.abs().max(hi.abs()).max_element()));
    (lo - grow, hi + grow)
}

/// The bounds of C ∩ A for one light (module doc).
fn reach_bounds(light: &GpuLight, (lo, hi): (Vec3, Vec3), real: (Vec3, Vec3)) -> Reach {
    if !(Vec4::from(light.position).is_finite() && Vec4::from(light.direction).is_finite()) {
        return Reach::Everywhere;
    }
    let corners = box_corners((lo, hi));
    let whole = (lo.min(real.0), hi.max(real.1));
    let mut points = corners.to_vec();
    if light.position[3] as u32 == KIND_DIRECTIONAL {
        // Past the diagonal of everything, a point swept along the light has left A.
        let Some(travel) = Vec4::from(light.direction).xyz().try_normalize() else {
            // No direction (never a valid light): the shading's ray test is then no bound.
            return Reach::Everywhere;
        };
        let reach = (whole.1 - whole.0).length() * 1.01;
        points.extend(corners.iter().map(|&b| b + travel * reach));
    } else {
        let at = Vec4::from(light.position).xyz();
        // Nearest point of the box to the light: 0 inside it.
        let nearest = (at.clamp(lo, hi) - at).length();
        if nearest <= 0.0 {
            return Reach::Everywhere;
        }
        let farthest = box_corners(whole)
            .iter()
            .map(|c| c.distance(at))
            .fold(0.0f32, f32::max);
        // Beyond t = farthest / nearest every point of the cone is farther from the light than
        // any point of A.
        let t = farthest / nearest * 1.01;
        points.extend(corners.iter().map(|&b| at + (b - at) * t));
    }
    let (cone_lo, cone_hi) = points
        .iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(l, h), &p| {
            (l.min(p), h.max(p))
        });
    let slack = Vec3::splat(1e-4 * (1.0 + whole.0.abs().max(whole.1.abs()).max_element()));
    let (a_lo, a_hi) = (cone_lo.max(real.0 - slack), cone_hi.min(real.1 + slack));
    if a_lo.cmple(a_hi).all() {
        Reach::Within((a_lo, a_hi))
    } else {
        Reach::Nowhere
    }
}

/// How far in front of the camera's near plane a point lies, in clip space: the camera's depth
/// is reversed (`gpu_scene::camera_uniform`), 1 at the near plane, so the plane is z = w.
fn before_near(clip: Vec4) -> f32 {
    clip.w - clip.z
}

/// The pixels the boxes can cover in the image, one pixel of margin around them: each box's
/// corners and the points where its edges cross the near plane ([`before_near`] = 0), projected.
fn screen_rect(view_proj: Mat4, (width, height): (u32, u32), boxes: &[(Vec3, Vec3)]) -> PixelRect {
    let (mut lo, mut hi) = (glam::Vec2::INFINITY, glam::Vec2::NEG_INFINITY);
    let mut include = |clip: Vec4| {
        let ndc = clip.xy() / clip.w;
        let px = glam::Vec2::new(
            (ndc.x * 0.5 + 0.5) * width as f32,
            (0.5 - ndc.y * 0.5) * height as f32,
        );
        lo = lo.min(px);
        hi = hi.max(px);
    };
    for &b in boxes {
        let clip = box_corners(b).map(|c| view_proj * c.extend(1.0));
        for (i, c) in clip.iter().enumerate() {
            let near_c = before_near(*c);
            if near_c >= 0.0 && c.w > 0.0 {
                include(*c);
            }
            for d in &clip[i + 1..] {
                let near_d = before_near(*d);
                if (near_c >= 0.0) != (near_d >= 0.0) {
                    let s = near_c / (near_c - near_d);
                    let on_plane = c.lerp(*d, s);
                    if on_plane.w > 0.0 {
                        include(on_plane);
                    }
                }
            }
        }
    }
    if !(lo.x <= hi.x && lo.y <= hi.y) {
        return PixelRect {
            x: 0,
            y: 0,
            width: 0,
            height: 0,
        };
    }
    let clamp = |v: f32, max: u32| v.clamp(0.0, max as f32) as u32;
    let (x0, y0) = (
        clamp(lo.x.floor() - 1.0, width),
        clamp(lo.y.floor() - 1.0, height),
    );
    let (x1, y1) = (
        clamp(hi.x.ceil() + 1.0, width),
        clamp(hi.y.ceil() + 1.0, height),
    );
    PixelRect {
        x: x0,
        y: y0,
        width: x1 - x0,
        height: y1 - y0,
    }
}

/// The triangles of `triangles` (indices into `positions`) that can cover a pixel of `rect`
/// in the image drawn with `view_proj`, appended to `out`: every triangle but those whose three
/// corners, all in front of the near plane, lie beyond the same edge of the rectangle (grown by
/// a pixel). Such a triangle is the hull of its corners' projections, so it misses the
/// rectangle, and the scissor would drop all it draws; llvmpipe still transforms and sets it up.
pub fn triangles_within(
    view_proj: Mat4,
    (width, height): (u32, u32),
    rect: PixelRect,
    positions: &[Vec3],
    triangles: &[u32],
    out: &mut Vec<u32>,
) {
    const LEFT: u8 = 1;
    const RIGHT: u8 = 2;
    const ABOVE: u8 = 4;
    const BELOW: u8 = 8;
    let (x0, y0) = (rect.x as f32 - 1.0, rect.y as f32 - 1.0);
    let (x1, y1) = (
        (rect.x + rect.width) as f32 + 1.0,
        (rect.y + rect.height) as f32 + 1.0,
    );
    let outside: Vec<u8> = positions
        .iter()
        .map(|p| {
            let clip = view_proj * p.extend(1.0);
            if !(before_near(clip) >= 0.0 && clip.w > 0.0) {
                // Behind the near plane (or not finite): the triangle is kept.
                return 0;
            }
            let x = (clip.x / clip.w * 0.5 + 0.5) * width as f32;
            let y = (0.5 - clip.y / clip.w * 0.5) * height as f32;
            let mut code = 0;
            if x < x0 {
                code |= LEFT;
            }
            if x > x1 {
                code |= RIGHT;
            }
            if y < y0 {
                code |= ABOVE;
            }
            if y > y1 {
                code |= BELOW;
            }
            code
        })
        .collect();
    for corners in triangles.chunks_exact(3) {
        let code = |i: u32| outside.get(i as usize).copied().unwrap_or(0);
        if code(corners[0]) & code(corners[1]) & code(corners[2]) == 0 {
            out.extend_from_slice(corners);
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use std::sync::Arc;

    use relight_core::light::Light;
    use relight_core::scene::Scene;
    use relight_core::{Frame, Image, PixelFormat, Timestamp};
    use serde_json::Map;

    use super::*;
    use crate::deferred::Deferred;
    use crate::differential::Differential;
    use crate::dlpv::Dlpv;
    use crate::dvct::Dvct;
    use crate::engine::{Engine, RelitFrame, SceneFrame};
    use crate::gpu::GpuContext;
    use crate::ibl::Ibl;
    use crate::offline::delta_pixels;
    use crate::test_scene as scene;

    /// An engine whose shared passes a test can reach.
    pub(crate) trait WithDeferred: Engine {
        fn deferred_mut(&mut self) -> &mut Deferred;
    }

    /// Δ, the composite, and the pixels the real meshes were drawn in, after `frames` frames
    /// of a still camera averaged over `accumulate`, with the engine's `params`.
    fn render(
        engine: &mut dyn WithDeferred,
        scene: &Arc<Scene>,
        cull: bool,
        (frames, accumulate): (u32, u32),
        params: &Map<String, serde_json::Value>,
    ) -> (Vec<Vec3>, Vec<u8>, Option<PixelRect>) {
        let mut params = params.clone();
        params.insert("accumulate".into(), accumulate.into());
        engine.set_params(&params);
        if !cull {
            engine.deferred_mut().without_shadow_reach_cull();
        }
        // Every 8-bit value in each channel, so that the camera's picture the composite keeps
        // outside the object's reach is checked against the shading pass's own.
        let mut color = Image::new(96, 72, PixelFormat::Rgb8);
        for (i, px) in color.as_u8_mut().unwrap().chunks_exact_mut(3).enumerate() {
            px.copy_from_slice(&[i as u8, (i * 7) as u8, (i * 13 / 5) as u8]);
        }
        let frame = SceneFrame {
            stamp: Timestamp::new(0, 0),
            seq: 0,
            color: Some(Arc::new(Frame::new(0, Timestamp::new(0, 0), color))),
            depth: None,
            scene: Some(scene.clone()),
        };
        let mut out = RelitFrame::default();
        for _ in 0..frames {
            engine.render(&frame, &mut out).expect("it renders");
        }
        (
            delta_pixels(&out.delta),
            out.composite.as_u8().unwrap().to_vec(),
            engine.deferred_mut().real_pixels(),
        )
    }

    /// Skipping the shadow-map lookups of pixels the object cannot shadow (`may_shadow`), and
    /// drawing the real meshes and shading only within the pixels where it can, changes no
    /// pixel of Δ or of the composite. `differential` under desk_box's light, under a low one
    /// whose long shadows graze the floor and reach the wall, and on a mean of four still
    /// frames at sub-pixel offsets (each drawn within its own pixels) held for two more;
    /// `ibl` on desk_box and under window_env's environment lights (directional).
    #[test]
    fn the_objects_reach_changes_no_pixel() {
        let ctx = Arc::new(GpuContext::new().expect("a GPU adapter (lavapipe in CI)"));
        let desk = scene("desk_box");
        let mut low = desk.clone();
        low.lights = vec![Light::Point {
            position_in_world: Vec3::new(0.9, 0.35, 0.6),
            intensity: Vec3::splat(2.0),
        }];
        let (desk, low, window) = (Arc::new(desk), Arc::new(low), Arc::new(scene("window_env")));
        let engine = |name: &str| -> Box<dyn WithDeferred> {
            match name {
                "ibl" => Box::new(Ibl::new(ctx.clone()).unwrap()),
                "dlpv" => Box::new(Dlpv::new(ctx.clone()).unwrap()),
                "dvct" => Box::new(Dvct::new(ctx.clone()).unwrap()),
                _ => Box::new(Differential::new(ctx.clone()).unwrap()),
            }
        };
        let cases = [
            ("differential", "desk_box", &desk, (1, 32)),
            ("differential", "low light", &low, (1, 32)),
            ("differential", "a mean held", &desk, (6, 4)),
            ("ibl", "desk_box", &desk, (1, 32)),
            ("ibl", "window_env", &window, (1, 32)),
            ("dlpv", "desk_box", &desk, (1, 32)),
            ("dvct", "desk_box", &desk, (1, 32)),
            ("dvct", "low light", &low, (1, 32)),
        ];
        // By default the light that the object blocks (and `dvct`'s far receivers) reaches
        // every real pixel; without it, the volume engines' volume and the shadows alone.
        let params = |engine_name: &str| {
            let params = match engine_name {
                "dlpv" | "ibl" => serde_json::json!({ "occlusion": "none" }),
                "dvct" => {
                    serde_json::json!({ "occlusion": "directional", "far_receivers": "none" })
                }
                _ => serde_json::json!({}),
            };
            params.as_object().cloned().unwrap_or_default()
        };
        for (engine_name, case, scene, frames) in cases {
            let name = format!("{engine_name}, {case}");
            let params = params(engine_name);
            let (culled, culled_composite, reach) =
                render(&mut *engine(engine_name), scene, true, frames, &params);
            let (full, full_composite, everywhere) =
                render(&mut *engine(engine_name), scene, false, frames, &params);
            assert_eq!(
                everywhere, None,
                "{name}: without the cull every pixel is drawn"
            );
            let reach = reach.expect("the object's reach is drawn alone");
            println!("{name}: the object can change {reach:?} of 96 × 72");
            assert!(
                reach.area() < 96 * 72,
                "{name}: {reach:?} is the whole image"
            );
            let shadowed = full.iter().filter(|d| d.x < -1e-4).count();
            assert!(
                shadowed > 50,
                "{name}: the object shadows {shadowed} pixels"
            );
            for (i, (a, b)) in culled.iter().zip(&full).enumerate() {
                assert_eq!(
                    a.to_array().map(f32::to_bits),
                    b.to_array().map(f32::to_bits),
                    "{name}: Δ at pixel {i}"
                );
            }
            for (i, (a, b)) in culled_composite
                .chunks_exact(3)
                .zip(full_composite.chunks_exact(3))
                .enumerate()
            {
                assert_eq!(a, b, "{name}: composite pixel {i}");
            }
        }
    }

    fn point_light(at: Vec3) -> GpuLight {
        GpuLight {
            position: at.extend(0.0).to_array(),
            direction: [0.0, -1.0, 0.0, 0.0],
            intensity: [1.0; 4],
            faces: [0, 6, 0, 0],
        }
    }

    fn face() -> GpuFace {
        GpuFace {
            view_proj: Mat4::IDENTITY.to_cols_array_2d(),
            axis: [0.0, -1.0, 0.0, 1.0],
            light: [0; 4],
        }
    }

    /// A camera 2 m in front of the origin looking at it, 60° vertical field of view.
    fn camera() -> Mat4 {
        let view = Mat4::look_at_rh(Vec3::new(0.0, 0.5, 2.0), Vec3::ZERO, Vec3::Y);
        Mat4::perspective_infinite_reverse_rh(60f32.to_radians(), 4.0 / 3.0, 0.01) * view
    }

    /// Under a light straight above a small object on a wide floor, the rectangle holds the
    /// object and its shadow on the floor, and leaves out the floor's far sides.
    #[test]
    fn a_light_above_reaches_the_floor_under_the_object_alone() {
        let object = (Vec3::new(-0.05, 0.0, -0.05), Vec3::new(0.05, 0.1, 0.05));
        let floor = (Vec3::new(-3.0, -0.001, -3.0), Vec3::new(3.0, 0.001, 3.0));
        let rect = reach_rect(
            camera(),
            (320, 240),
            &[point_light(Vec3::new(0.0, 1.0, 0.0))],
            &[face()],
            512,
            (object, &[]),
            floor,
        );
        assert!(!rect.is_empty());
        assert!(
            rect.area() * 20 < 320 * 240,
            "{rect:?} covers more than a twentieth of the image"
        );
        // The object's centre projects inside the rectangle.
        let centre = camera() * Vec3::new(0.0, 0.05, 0.0).extend(1.0);
        let px = (centre.x / centre.w * 0.5 + 0.5) * 320.0;
        let py = (0.5 - centre.y / centre.w * 0.5) * 240.0;
        assert!(px > rect.x as f32 && px < (rect.x + rect.width) as f32);
        assert!(py > rect.y as f32 && py < (rect.y + rect.height) as f32);
    }

    /// A triangle left out covers no point of the rectangle: on a 40 × 40 grid in front of the
    /// camera, points spread over each dropped triangle all project outside it, and the
    /// rectangle keeps a small share of the grid.
    #[test]
    fn the_triangles_left_out_miss_the_rectangle() {
        let n = 40;
        let positions: Vec<Vec3> = (0..=n)
            .flat_map(|j| {
                (0..=n).map(move |i| {
                    Vec3::new(
                        i as f32 / n as f32 * 4.0 - 2.0,
                        -0.2,
                        j as f32 / n as f32 * 4.0 - 2.5,
                    )
                })
            })
            .collect();
        let at = |i: u32, j: u32| j * (n + 1) + i;
        let triangles: Vec<u32> = (0..n)
            .flat_map(|j| {
                (0..n).flat_map(move |i| {
                    [
                        at(i, j),
                        at(i + 1, j),
                        at(i, j + 1),
                        at(i + 1, j),
                        at(i + 1, j + 1),
                        at(i, j + 1),
                    ]
                })
            })
            .collect();
        let rect = PixelRect {
            x: 120,
            y: 140,
            width: 60,
            height: 30,
        };
        let mut kept = Vec::new();
        triangles_within(
            camera(),
            (320, 240),
            rect,
            &positions,
            &triangles,
            &mut kept,
        );
        let total = triangles.len() / 3;
        let kept_count = kept.len() / 3;
        assert!(
            kept_count > 0 && kept_count * 4 < total,
            "{kept_count} of {total} kept"
        );
        let kept: std::collections::HashSet<&[u32]> = kept.chunks_exact(3).collect();
        for corners in triangles.chunks_exact(3).filter(|c| !kept.contains(c)) {
            let [a, b, c] = [0, 1, 2].map(|k| positions[corners[k] as usize]);
            for (u, v) in (0..=8).flat_map(|u| (0..=8 - u).map(move |v| (u, v))) {
                let (u, v) = (u as f32 / 8.0, v as f32 / 8.0);
                let clip = camera() * (a + (b - a) * u + (c - a) * v).extend(1.0);
                let x = (clip.x / clip.w * 0.5 + 0.5) * 320.0;
                let y = (0.5 - clip.y / clip.w * 0.5) * 240.0;
                let inside = x >= rect.x as f32
                    && x <= (rect.x + rect.width) as f32
                    && y >= rect.y as f32
                    && y <= (rect.y + rect.height) as f32;
                assert!(!inside, "{corners:?} was left out but covers ({x}, {y})");
            }
        }
    }

    /// A light inside the object, a directional light without a direction, or a light that is
    /// not finite, reaches every pixel: the shading's ray test bounds nothing there.
    #[test]
    fn a_light_inside_the_object_or_malformed_reaches_everywhere() {
        let object = (Vec3::splat(-0.1), Vec3::splat(0.1));
        let room = (Vec3::splat(-5.0), Vec3::splat(5.0));
        let directional = GpuLight {
            position: [0.0, 0.0, 0.0, KIND_DIRECTIONAL as f32],
            direction: [0.0; 4],
            ..point_light(Vec3::ZERO)
        };
        for light in [
            point_light(Vec3::ZERO),
            directional,
            point_light(Vec3::new(f32::NAN, 1.0, 0.0)),
        ] {
            let rect = reach_rect(
                camera(),
                (320, 240),
                &[light],
                &[face()],
                512,
                (object, &[]),
                room,
            );
            assert_eq!(rect, PixelRect::full(320, 240), "{light:?}");
        }
    }

    /// A box reaching behind the camera is clipped at its near plane, not mirrored: the
    /// rectangle spans the image.
    #[test]
    fn a_box_behind_the_camera_is_clipped_at_the_near_plane() {
        let around_camera = (Vec3::new(-0.1, 0.4, 1.0), Vec3::new(0.1, 0.6, 3.0));
        let rect = screen_rect(camera(), (320, 240), &[around_camera]);
        assert_eq!(rect, PixelRect::full(320, 240));
    }
}
