//! The shadow maps every engine shares (`Deferred`): kept across frames while what they are drawn
//! from holds, redrawn when it changes, and drawn from the scene's shadow proxy where it has one.

mod support;

use std::sync::Arc;

use glam::Vec3;
use relight_core::light::Light;
use relight_core::scene::{Mesh, Scene};
use relight_engines::shadow_proxy::{SHADOW_PROXY_ERROR_M, decimate};
use relight_engines::{Engine, RelitFrame};
use support::{engine, engine_with, frame, load_scene};

fn render(engine: &mut Box<dyn Engine>, scene: &Arc<Scene>) -> RelitFrame {
    let mut out = RelitFrame::default();
    engine
        .render(&frame(scene.clone(), 80, 60), &mut out)
        .unwrap_or_else(|e| panic!("{e}"));
    out
}

fn moved_light(scene: &Scene, by: Vec3) -> Scene {
    let mut scene = scene.clone();
    for light in &mut scene.lights {
        if let Light::Point {
            position_in_world, ..
        } = light
        {
            *position_in_world += by;
        }
    }
    scene
}

/// `scene` with a second point light, beside and above its own.
fn with_second_light(scene: &Scene) -> Scene {
    let mut scene = scene.clone();
    scene.lights.push(Light::Point {
        position_in_world: Vec3::new(-0.5, 0.9, 0.4),
        intensity: Vec3::splat(1.0),
    });
    scene
}

/// `scene` with its last light moved.
fn moved_last_light(scene: &Scene, by: Vec3) -> Scene {
    let mut scene = scene.clone();
    if let Some(Light::Point {
        position_in_world, ..
    }) = scene.lights.last_mut()
    {
        *position_in_world += by;
    }
    scene
}

/// The bytes the shadow-map pass moved for a frame (0: not drawn).
fn shadow_bytes(out: &RelitFrame) -> f64 {
    out.work
        .iter()
        .filter(|w| w.pass == "shadow")
        .map(|w| w.work.bytes)
        .sum()
}

fn moved_object(scene: &Scene, by: Vec3) -> Scene {
    let mut scene = scene.clone();
    for mesh in scene.meshes.iter_mut().filter(|m| m.is_virtual) {
        for p in &mut mesh.positions_in_world {
            *p += by;
        }
    }
    scene
}

fn moved_camera(scene: &Scene, by: Vec3) -> Scene {
    let mut scene = scene.clone();
    scene.camera.world_from_camera.translation += by;
    scene
}

fn ran(out: &RelitFrame, pass: &str) -> bool {
    out.timings.iter().any(|t| t.pass == pass)
}

/// A sequence of frames where the light changes, then nothing, then only the camera, then the
/// object: every frame's Δ and composite are bit-identical to a fresh engine's on that frame
/// alone, so nothing kept from an earlier frame is ever stale. The shadow maps, and what
/// `dvct` and `dlpv` derive from them alone (voxels and their radiance, the propagated
/// volume), are recomputed only on the frames whose scene or lights changed: not on a frame
/// equal to the last (a new `Arc`, as the live scene makes every frame), nor on one where the
/// camera alone moved. The same holds for `dir`'s VPLs and their imperfect shadow maps. When
/// one of two lights moves, only its own faces are redrawn.
#[test]
fn kept_shadow_maps_and_volumes_equal_freshly_drawn_ones() {
    let desk = with_second_light(&load_scene("desk_box"));
    let lit = moved_light(&desk, Vec3::new(0.2, 0.0, 0.0));
    let moved = moved_object(
        &moved_camera(&lit, Vec3::new(0.05, 0.0, 0.0)),
        Vec3::X * 0.05,
    );
    let frames = [
        desk.clone(),
        lit.clone(),
        lit.clone(),
        moved_camera(&lit, Vec3::new(0.05, 0.0, 0.0)),
        moved.clone(),
        moved_last_light(&moved, Vec3::new(0.0, 0.0, 0.1)),
    ];
    let recomputed = [true, true, false, false, true, true];
    // Frames where one light of the two moved: half the faces are drawn.
    let one_light = [false, false, false, false, false, true];
    // Without the sub-pixel accumulation, whose still frames differ from a fresh engine's
    // first by design.
    let small = serde_json::json!({"volume_size": 16, "steps": 8, "accumulate": 1});
    for (name, params, volume_pass) in [
        ("differential", serde_json::json!({"accumulate": 1}), None),
        (
            "dvct",
            serde_json::json!({"volume_size": 16, "accumulate": 1}),
            Some("gpu.voxelize"),
        ),
        ("dlpv", small, Some("gpu.propagate")),
        (
            "dir",
            serde_json::json!({"vpl_count": 64, "accumulate": 1}),
            Some("gpu.vpls"),
        ),
    ] {
        let mut kept = engine_with(name, params.clone());
        for (i, scene) in frames.iter().enumerate() {
            let scene = Arc::new(scene.clone());
            let out = render(&mut kept, &scene);
            let fresh = render(&mut engine_with(name, params.clone()), &scene);
            assert!(out.delta == fresh.delta, "{name}: frame {i}'s Δ");
            assert!(
                out.composite == fresh.composite,
                "{name}: frame {i}'s composite"
            );
            if ran(&fresh, "gpu.shadow") {
                assert_eq!(ran(&out, "gpu.shadow"), recomputed[i], "{name}: frame {i}");
                if one_light[i] {
                    assert_eq!(
                        2.0 * shadow_bytes(&out),
                        shadow_bytes(&fresh),
                        "{name}: frame {i} redraws one light's faces"
                    );
                }
                assert_eq!(
                    ran(&out, "gpu.rsm"),
                    recomputed[i] && name != "differential",
                    "{name}: frame {i}'s RSM"
                );
                if let Some(pass) = volume_pass {
                    assert_eq!(ran(&out, pass), recomputed[i], "{name}: frame {i}'s {pass}");
                }
            }
        }
    }
}

/// Every real triangle of `mesh` split into 4^`levels` by its edge midpoints.
fn subdivided(mesh: &Mesh, levels: u32) -> Mesh {
    let mut mesh = mesh.clone();
    for _ in 0..levels {
        let mut triangles = Vec::new();
        // One midpoint per edge, shared by the triangles on both sides.
        let mut midpoints = std::collections::HashMap::new();
        for [a, b, c] in std::mem::take(&mut mesh.triangles) {
            let mut mid = |i: u32, j: u32| {
                *midpoints.entry((i.min(j), i.max(j))).or_insert_with(|| {
                    let (i, j) = (i as usize, j as usize);
                    mesh.positions_in_world
                        .push((mesh.positions_in_world[i] + mesh.positions_in_world[j]) / 2.0);
                    mesh.normals_in_world
                        .push((mesh.normals_in_world[i] + mesh.normals_in_world[j]).normalize());
                    mesh.positions_in_world.len() as u32 - 1
                })
            };
            let (ab, bc, ca) = (mid(a, b), mid(b, c), mid(c, a));
            triangles.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        }
        mesh.triangles = triangles;
    }
    mesh
}

/// The real meshes as one (what a depth surface is).
fn merged(meshes: &[Mesh]) -> Mesh {
    let mut out = Mesh {
        name: "real".into(),
        triangles: Vec::new(),
        positions_in_world: Vec::new(),
        normals_in_world: Vec::new(),
        material: meshes[0].material,
        is_virtual: false,
        vertex_albedo: Vec::new(),
    };
    for mesh in meshes {
        let first = out.positions_in_world.len() as u32;
        out.positions_in_world.extend(&mesh.positions_in_world);
        out.normals_in_world.extend(&mesh.normals_in_world);
        out.triangles
            .extend(mesh.triangles.iter().map(|t| t.map(|i| i + first)));
    }
    out
}

/// The desk with its real meshes finely tessellated (as a depth surface is), drawn into the
/// shadow maps once as they are and once through their decimated proxy. The proxy has a small
/// fraction of the triangles and lies within 2 mm of the surface, under the shading's depth
/// bias, so Δ may differ only by rounding: the f16 step of Δ (2⁻¹⁰ relative) on a pixel
/// whose shadow test sits at the bias, which bounds the relative L2 difference by 1 %.
#[test]
fn a_decimated_shadow_proxy_casts_the_same_shadows() {
    let mut desk = load_scene("desk_box");
    let (real, object): (Vec<Mesh>, Vec<Mesh>) = desk.meshes.drain(..).partition(|m| !m.is_virtual);
    let fine: Vec<Mesh> = real.iter().map(|m| subdivided(m, 4)).collect();
    desk.meshes = fine.iter().cloned().chain(object).collect();
    let proxy = decimate(&merged(&fine), SHADOW_PROXY_ERROR_M);
    let fine_triangles: usize = fine.iter().map(|m| m.triangles.len()).sum();
    eprintln!("{fine_triangles} → {} triangles", proxy.triangles.len());
    assert!(
        proxy.triangles.len() * 20 < fine_triangles,
        "{} of {fine_triangles} triangles kept",
        proxy.triangles.len()
    );
    let with_proxy = Scene {
        shadow_proxy: Some(Arc::new(proxy)),
        ..desk.clone()
    };
    let full = render(&mut engine("differential"), &Arc::new(desk));
    let decimated = render(&mut engine("differential"), &Arc::new(with_proxy));
    let (a, b) = (
        relight_engines::offline::delta_pixels(&full.delta),
        relight_engines::offline::delta_pixels(&decimated.delta),
    );
    let norm = |v: &[Vec3]| v.iter().map(|d| d.length_squared()).sum::<f32>().sqrt();
    let difference: Vec<Vec3> = a.iter().zip(&b).map(|(a, b)| *a - *b).collect();
    let relative = norm(&difference) / norm(&a);
    eprintln!("relative L2 of the Δ difference {relative:.5}");
    assert!(norm(&a) > 0.0, "the object casts a shadow");
    assert!(relative < 0.01, "relative L2 {relative}");
}

/// The shadow maps draw the proxy in place of the real meshes. The real meshes as their own
/// proxy change nothing; a proxy with a real roof between the lamp and the desk (a roof the
/// camera does not see) puts the whole desk in shadow in both solutions, so the object's
/// shadow, and with it Δ, is gone.
#[test]
fn the_shadow_maps_draw_the_proxy_not_the_real_meshes() {
    let desk = load_scene("desk_box");
    let real: Vec<Mesh> = desk
        .meshes
        .iter()
        .filter(|m| !m.is_virtual)
        .cloned()
        .collect();
    let with_proxy = |meshes: Vec<Mesh>| {
        Arc::new(Scene {
            shadow_proxy: Some(Arc::new(merged(&meshes))),
            ..desk.clone()
        })
    };
    let roof = Mesh::cuboid(
        "roof",
        Vec3::new(-1.0, 1.0, -0.8),
        Vec3::new(1.0, 1.02, 1.2),
        0,
        false,
    );
    let full = render(&mut engine("differential"), &Arc::new(desk.clone()));
    let same = render(&mut engine("differential"), &with_proxy(real.clone()));
    let roofed = render(
        &mut engine("differential"),
        &with_proxy(real.into_iter().chain([roof]).collect()),
    );
    assert!(
        full.delta == same.delta,
        "the real meshes as their own proxy"
    );
    let norm = |out: &RelitFrame| {
        relight_engines::offline::delta_pixels(&out.delta)
            .iter()
            .map(|d| d.length_squared())
            .sum::<f32>()
            .sqrt()
    };
    assert!(norm(&full) > 0.0, "the object casts a shadow");
    assert!(
        norm(&roofed) < 0.05 * norm(&full),
        "under the roof: {} against {}",
        norm(&roofed),
        norm(&full)
    );
}

/// The direct light is shadowed by the shadow maps alone: a VPL engine's reflective shadow maps
/// (here 16² a face, far too coarse to shadow with) are drawn beside them and change nothing in
/// the direct Δ, and each set has its own size.
#[test]
fn the_reflective_shadow_maps_do_not_shadow_the_direct_light() {
    use relight_engines::deferred::{Deferred, MapSizes, ShadeOptions};
    use relight_engines::gpu::GpuContext;

    let ctx = Arc::new(GpuContext::new().expect("a GPU adapter (lavapipe in CI)"));
    let scene = Arc::new(load_scene("desk_box"));
    let options = ShadeOptions {
        shadow_bias_texels: 1.5,
        direct_delta: true,
    };
    let direct = |sizes: MapSizes| {
        let mut deferred = Deferred::new(ctx.clone());
        deferred.set_accumulate(1);
        let mut out = RelitFrame::default();
        deferred
            .prepare("test", &frame(scene.clone(), 80, 60), &mut out, sizes)
            .unwrap();
        let shadows = deferred.shadow_maps().map(|s| (s.size, s.mu.width));
        let rsm = deferred.light_buffers().map(|(_, _, _, mu)| mu.width);
        deferred.finish(options, &mut out).unwrap();
        (out.delta, shadows, rsm)
    };
    let (alone, shadows, rsm) = direct(MapSizes::shadows(512));
    assert_eq!((shadows, rsm), (Some((512, 512)), None));
    let (beside, shadows, rsm) = direct(MapSizes::with_rsm(512, 16));
    assert_eq!((shadows, rsm), (Some((512, 512)), Some(16)));
    assert!(
        relight_engines::offline::delta_pixels(&alone)
            .iter()
            .any(|d| d.length() > 0.0),
        "the object casts a shadow"
    );
    assert!(
        alone == beside,
        "the direct Δ changed with the RSM beside it"
    );
}
