//! The scene engines relight live: the real surface measured by the depth camera (or the scene
//! file's own real meshes, for a known room), the virtual object(s), lights and camera pose from
//! a scene file, and the pocket lamp where it is now.
//!
//! The camera pose is the scene file's until the daemon's tracker registers the camera
//! ([`LiveScene::set_world_from_camera`]), frame by frame. The depth-derived surface has the
//! configured diffuse albedo, or, with [`LiveScene::measure_albedo`], what DLPV's eq. 1 measures
//! from the colour camera under the frame's lights, per vertex ([`crate::surface_albedo`]).

use std::sync::Arc;

use glam::Vec3;
use relight_core::camera::Pinhole;
use relight_core::light::Light;
use relight_core::scene::{EnvironmentMap, Material, Mesh, Scene};
use relight_core::{Image, LampState, Pose};
use relight_recon::irradiance::project_sh9;

use crate::shadow_proxy::{HeldProxy, ProxyHold};
use crate::surface_albedo::{AlbedoReport, DepthGrid, SurfaceAlbedo};

/// Where the real geometry comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RealGeometry {
    /// Triangulated from each depth frame.
    Depth,
    /// The scene file's real meshes (a proxy of a known room).
    Scene,
}

/// Where the real scene's light comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LightSource {
    /// The scene file's lights and environment map (a known room).
    Scene,
    /// The light probe's estimate: its environment map for the engines that sample one (`ibl`,
    /// `dir`), its median-cut directional lights for the others; the scene file's lights and map
    /// are left out (the probe sees them). The tracked lamp is added as a point light.
    Probe,
}

/// Neighbouring depth samples further apart than this (relative) are not joined: a depth edge.
const MAX_RELATIVE_JUMP: f32 = 0.05;

#[derive(Debug)]
pub struct LiveScene {
    base: Scene,
    real: RealGeometry,
    real_material: usize,
    /// The scene file's real meshes, used when depth is unusable (with [`RealGeometry::Depth`]).
    proxy: Vec<Mesh>,
    light_source: LightSource,
    depth_camera: Option<Pinhole>,
    stride: u32,
    /// The scene without per-frame parts, shared while nothing changes (engines cache uploads
    /// by `Arc` identity).
    fixed: Option<Arc<Scene>>,
    /// The lamp's last reported state: its serial line reports less often than the cameras run,
    /// so most frame sets carry no lamp message and the lamp must not blink off in between.
    lamp: Option<LampState>,
    /// Measures the depth surface's albedo, when the colour camera's response is known.
    albedo: Option<SurfaceAlbedo>,
    /// The scene file's environment map as an SH light (what albedo estimation is told of it),
    /// projected when measurement starts.
    environment_sh: Option<Light>,
    /// The depth surface decimated for the shadow maps ([`Scene::shadow_proxy`]).
    shadow_proxy: HeldProxy,
    /// The depth stage said the next frame's surface is the last one's ([`Self::hold_surface`]).
    surface_held: bool,
    /// [`Scene::surface_revision`] of the depth surface: advanced on every frame the depth
    /// stage did not hold the surface.
    surface_revision: u64,
}

impl LiveScene {
    /// `base`: the scene file; `depth_camera`: the depth camera's intrinsics (registered to the
    /// colour camera); `stride`: use every `stride`-th depth pixel per axis.
    pub fn new(
        mut base: Scene,
        real: RealGeometry,
        real_albedo: f32,
        depth_camera: Option<Pinhole>,
        stride: u32,
    ) -> Self {
        if let Some(camera) = depth_camera {
            // The colour camera's field of view (registered depth shares it).
            base.camera.yfov_rad = camera.yfov_rad() as f32;
        }
        let real_material = base.materials.len();
        base.materials.push(Material {
            name: "measured surface".into(),
            albedo: Vec3::splat(real_albedo.clamp(0.0, 1.0)),
            ..Material::default()
        });
        let mut proxy = Vec::new();
        if real == RealGeometry::Depth {
            (base.meshes, proxy) = base.meshes.into_iter().partition(|m| m.is_virtual);
        }
        Self {
            base,
            real,
            real_material,
            proxy,
            light_source: LightSource::Scene,
            depth_camera,
            stride: stride.max(1),
            fixed: None,
            lamp: None,
            albedo: None,
            environment_sh: None,
            shadow_proxy: HeldProxy::new(ProxyHold::default()),
            surface_held: false,
            surface_revision: 0,
        }
    }

    /// The depth stage merged the next frame's depth with its history without a reset: the
    /// real surface has not materially changed, so the shadow maps' proxy of it may be kept.
    /// Holds for one [`frame`](Self::frame).
    pub fn hold_surface(&mut self) {
        self.surface_held = true;
    }

    /// Shadow proxies built so far (a held one is not counted again).
    pub fn shadow_proxies_built(&self) -> u64 {
        self.shadow_proxy.built()
    }

    /// Measure the depth surface's albedo from now on (with [`RealGeometry::Depth`]).
    pub fn measure_albedo(&mut self, albedo: SurfaceAlbedo) {
        self.environment_sh = self
            .base
            .environment
            .as_ref()
            .and_then(|env| project_sh9(env).ok())
            .map(|sh| Light::Environment {
                sh,
                intensity_scale: 1.0,
            });
        self.albedo = Some(albedo);
    }

    /// Make the albedo measurement's estimates on a thread of their own from now on
    /// ([`SurfaceAlbedo::estimate_on_own_thread`]); nothing without a measurement.
    pub fn albedo_on_own_thread(&mut self) -> std::io::Result<()> {
        match self.albedo.as_mut() {
            Some(albedo) => albedo.estimate_on_own_thread(),
            None => Ok(()),
        }
    }

    /// What the albedo measurement did on the last frame, when it runs.
    pub fn albedo_report(&self) -> Option<AlbedoReport> {
        self.albedo.as_ref().map(SurfaceAlbedo::report)
    }

    /// Every light of the next frame as an estimator sees it: discrete lights (the probe's
    /// median-cut lights stand for its map), the lamp, and a scene file's map as SH. `None`
    /// before the probe's first estimate: the lights are not known yet.
    fn lights_for_albedo(&self) -> Option<Vec<Light>> {
        let mut lights = self.lights();
        match self.light_source {
            LightSource::Probe if self.base.environment_lights.is_empty() => return None,
            LightSource::Probe => lights.extend(self.base.environment_lights.iter().copied()),
            LightSource::Scene => lights.extend(self.environment_sh),
        }
        Some(lights)
    }

    /// Take the real scene's light from `source` from now on.
    pub fn set_light_source(&mut self, source: LightSource) {
        if source == LightSource::Probe {
            self.base.lights.clear();
            self.base.environment = None;
        }
        self.light_source = source;
        self.fixed = None;
    }

    /// The probe's newest environment map and its directional lights (used with
    /// [`LightSource::Probe`]).
    pub fn set_probe_estimate(&mut self, environment: &EnvironmentMap, lights: &[Light]) {
        if self.light_source == LightSource::Probe {
            self.base.environment = Some(environment.clone());
            self.base.environment_lights = lights.to_vec();
            self.fixed = None;
        }
    }

    /// The lights the next frame is lit by: the scene file's (with [`LightSource::Scene`]) and
    /// the lamp as last reported.
    pub fn lights(&self) -> Vec<Light> {
        self.base
            .lights
            .iter()
            .copied()
            .chain(self.lamp_light())
            .collect()
    }

    /// The tracked lamp as a point light, while it is on and where it was last reported.
    pub fn lamp_light(&self) -> Option<Light> {
        self.lamp
            .filter(|l| l.on && l.position_in_world.is_finite())
            .map(|l| Light::Point {
                position_in_world: l.position_in_world,
                intensity: l.intensity,
            })
    }

    /// Where the camera is now (glTF convention): the scene file's pose until the tracker sets
    /// one.
    pub fn world_from_camera(&self) -> Pose {
        self.base.camera.world_from_camera
    }

    /// The camera's registered pose for the next frame.
    pub fn set_world_from_camera(&mut self, world_from_camera: Pose) {
        if self.base.camera.world_from_camera != world_from_camera {
            self.base.camera.world_from_camera = world_from_camera;
            self.fixed = None;
        }
    }

    /// The scene for one frame set. With [`RealGeometry::Depth`] and no usable depth (`None`,
    /// nothing triangulated, or no depth calibration) the scene file's real meshes stand in as a
    /// proxy of the room; `None` when it has none. `color` is the set's colour image (what albedo
    /// is measured from). `lamp` is the set's lamp message, if it has one; without one the lamp
    /// keeps its last reported state.
    pub fn frame(
        &mut self,
        depth: Option<&Image>,
        color: Option<&Image>,
        lamp: Option<&LampState>,
    ) -> Option<Arc<Scene>> {
        if let Some(lamp) = lamp {
            self.lamp = Some(*lamp);
        }
        let surface_held = std::mem::take(&mut self.surface_held);
        let lamp_light = self.lamp_light();
        if self.real == RealGeometry::Scene && lamp_light.is_none() {
            return Some(
                self.fixed
                    .get_or_insert_with(|| Arc::new(self.base.clone()))
                    .clone(),
            );
        }
        let mut scene = self.base.clone();
        scene.lights.extend(lamp_light);
        if self.real == RealGeometry::Depth {
            let world_from_camera = scene.camera.world_from_camera;
            let surface = depth
                .zip(self.depth_camera)
                .map(|(depth, camera)| {
                    let (mesh, grid) = depth_surface(
                        depth,
                        &camera,
                        &world_from_camera,
                        self.real_material,
                        self.stride,
                    );
                    (mesh, grid, camera)
                })
                .filter(|(mesh, _, _)| !mesh.triangles.is_empty());
            match surface {
                Some((mut mesh, grid, camera)) => {
                    let lights = self
                        .albedo
                        .is_some()
                        .then(|| self.lights_for_albedo())
                        .flatten();
                    if let Some(albedo) = &mut self.albedo {
                        // Without known lights the last estimate is carried, nothing measured.
                        albedo.apply(
                            &mut mesh,
                            &grid,
                            &camera,
                            &world_from_camera,
                            color.filter(|_| lights.is_some()),
                            lights.as_deref().unwrap_or_default(),
                        );
                    }
                    scene.shadow_proxy = Some(self.shadow_proxy.proxy(
                        &mesh,
                        &world_from_camera,
                        surface_held,
                    ));
                    if !surface_held {
                        self.surface_revision += 1;
                    }
                    scene.surface_revision = Some(self.surface_revision);
                    scene.meshes.insert(0, mesh);
                }
                None if !self.proxy.is_empty() => {
                    self.shadow_proxy.drop_held();
                    scene.meshes.splice(0..0, self.proxy.iter().cloned());
                }
                None => {
                    self.shadow_proxy.drop_held();
                    return None;
                }
            }
        }
        Some(Arc::new(scene))
    }
}

/// Triangulate a depth image (any depth format; invalid = 0, NaN or missing) seen by `camera`
/// (OpenCV optical frame) at `world_from_camera` (glTF convention) into a real mesh: two
/// triangles per 2 × 2 block of valid samples whose depths agree within 5 %, vertex normals from
/// the neighbouring positions, facing the camera. The mesh takes every `stride`-th pixel of
/// `camera`'s; `depth` holds either all of `camera`'s pixels or only those
/// ([`Image::subsampled`] by `stride`, as the depth stage reconstructs them), and gives the same
/// mesh either way.
pub fn depth_mesh(
    depth: &Image,
    camera: &Pinhole,
    world_from_camera: &Pose,
    material: usize,
    stride: u32,
) -> Mesh {
    depth_surface(depth, camera, world_from_camera, material, stride).0
}

/// [`depth_mesh`], and the grid of depth samples its vertices come from.
pub fn depth_surface(
    depth: &Image,
    camera: &Pinhole,
    world_from_camera: &Pose,
    material: usize,
    stride: u32,
) -> (Mesh, DepthGrid) {
    let stride = stride.max(1);
    let grid = camera.subsampled(stride);
    let sampled = stride > 1 && (depth.width(), depth.height()) == (grid.width, grid.height);
    let step = if sampled { 1 } else { stride };
    let (w, h) = (depth.width().div_ceil(step), depth.height().div_ceil(step));
    let at = |x: u32, y: u32| -> Option<Vec3> {
        let (px, py) = (x * stride, y * stride);
        let z = depth
            .depth_m(x * step, y * step)
            .filter(|z| z.is_finite() && *z > 0.0)?;
        let optical = Vec3::new(
            ((f64::from(px) - camera.cx) / camera.fx) as f32 * z,
            ((f64::from(py) - camera.cy) / camera.fy) as f32 * z,
            z,
        );
        Some(Vec3::new(optical.x, -optical.y, -optical.z))
    };
    let mut index = vec![u32::MAX; (w * h) as usize];
    let mut positions = Vec::new();
    let mut in_camera = Vec::new();
    for y in 0..h {
        for x in 0..w {
            if let Some(p) = at(x, y) {
                index[(y * w + x) as usize] = positions.len() as u32;
                in_camera.push(p);
                positions.push(world_from_camera.transform_point(p));
            }
        }
    }
    let joined = |a: Vec3, b: Vec3| {
        let (za, zb) = (-a.z, -b.z);
        (za - zb).abs() <= MAX_RELATIVE_JUMP * za.min(zb)
    };
    let mut triangles = Vec::new();
    for y in 0..h.saturating_sub(1) {
        for x in 0..w.saturating_sub(1) {
            let i = |dx: u32, dy: u32| index[((y + dy) * w + x + dx) as usize];
            let quad = [i(0, 0), i(1, 0), i(0, 1), i(1, 1)];
            for tri in [[quad[0], quad[2], quad[1]], [quad[1], quad[2], quad[3]]] {
                if tri.contains(&u32::MAX) {
                    continue;
                }
                let [a, b, c] = tri.map(|k| in_camera[k as usize]);
                if joined(a, b) && joined(b, c) && joined(a, c) {
                    triangles.push(tri);
                }
            }
        }
    }
    let mut normals = vec![Vec3::ZERO; positions.len()];
    for tri in &triangles {
        let [a, b, c] = tri.map(|k| positions[k as usize]);
        let n = (b - a).cross(c - a);
        for k in tri {
            normals[*k as usize] += n;
        }
    }
    let eye = world_from_camera.translation;
    for (n, p) in normals.iter_mut().zip(&positions) {
        let unit = n.normalize_or_zero();
        *n = if unit.dot(eye - *p) < 0.0 {
            -unit
        } else {
            unit
        };
    }
    let mesh = Mesh {
        name: "depth surface".into(),
        positions_in_world: positions,
        normals_in_world: normals,
        triangles,
        material,
        is_virtual: false,
        vertex_albedo: Vec::new(),
    };
    let grid = DepthGrid {
        width: w,
        height: h,
        stride,
        vertex_of_cell: index
            .iter()
            .map(|i| (*i != u32::MAX).then_some(*i))
            .collect(),
    };
    (mesh, grid)
}

#[cfg(test)]
mod tests {
    use relight_core::PixelFormat;

    use super::*;

    fn camera() -> Pinhole {
        Pinhole {
            width: 8,
            height: 6,
            fx: 8.0,
            fy: 8.0,
            cx: 3.5,
            cy: 2.5,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        }
    }

    #[test]
    fn a_flat_wall_becomes_a_flat_mesh_facing_the_camera() {
        let mut depth = Image::new(8, 6, PixelFormat::DepthF32M);
        depth.as_f32_mut().unwrap().fill(2.0);
        let mesh = depth_mesh(&depth, &camera(), &Pose::IDENTITY, 0, 1);
        assert_eq!(mesh.positions_in_world.len(), 48);
        assert_eq!(mesh.triangles.len(), 2 * 7 * 5);
        for (p, n) in mesh.positions_in_world.iter().zip(&mesh.normals_in_world) {
            assert!((p.z + 2.0).abs() < 1e-6, "{p}");
            assert!((*n - Vec3::Z).length() < 1e-5, "{n}");
        }
    }

    /// The depth stage hands over only the pixels the mesh takes; the mesh and its grid are
    /// the same as from the whole image.
    #[test]
    fn a_subsampled_depth_gives_the_same_mesh_as_the_whole_image() {
        let mut depth = Image::new(8, 6, PixelFormat::DepthF32M);
        for (i, z) in depth.as_f32_mut().unwrap().iter_mut().enumerate() {
            // A slope with a hole and a step, so joining and skipping both happen.
            *z = match i {
                10 => 0.0,
                i if i % 8 >= 6 => 3.0,
                i => 2.0 + 0.001 * i as f32,
            };
        }
        let pose = Pose::from_translation(Vec3::new(0.1, 0.2, 0.3));
        for stride in [2, 3] {
            let whole = depth_surface(&depth, &camera(), &pose, 0, stride);
            let part = depth_surface(&depth.subsampled(stride), &camera(), &pose, 0, stride);
            assert_eq!(whole, part, "stride {stride}");
            assert!(!whole.0.triangles.is_empty());
        }
    }

    /// A flat wall 2 m in front of [`camera`], and a live scene of it with nothing else.
    fn flat_wall() -> (Image, LiveScene) {
        let mut depth = Image::new(8, 6, PixelFormat::DepthF32M);
        depth.as_f32_mut().unwrap().fill(2.0);
        let base = Scene {
            name: "t".into(),
            meshes: Vec::new(),
            materials: Vec::new(),
            camera: relight_core::scene::SceneCamera {
                world_from_camera: Pose::IDENTITY,
                yfov_rad: 1.0,
                width: 8,
                height: 6,
            },
            lights: Vec::new(),
            environment: None,
            environment_lights: Vec::new(),
            shadow_proxy: None,
            surface_revision: None,
        };
        let live = LiveScene::new(base, RealGeometry::Depth, 0.5, Some(camera()), 1);
        (depth, live)
    }

    #[test]
    fn the_lamp_holds_its_last_state_between_reports() {
        let (depth, mut live) = flat_wall();
        let lamp = LampState {
            on: true,
            position_in_world: Vec3::Y,
            intensity: Vec3::ONE,
        };
        assert!(
            live.frame(Some(&depth), None, None)
                .unwrap()
                .lights
                .is_empty()
        );
        assert_eq!(
            live.frame(Some(&depth), None, Some(&lamp))
                .unwrap()
                .lights
                .len(),
            1
        );
        assert_eq!(
            live.frame(Some(&depth), None, None).unwrap().lights.len(),
            1,
            "held"
        );
        let off = LampState { on: false, ..lamp };
        assert!(
            live.frame(Some(&depth), None, Some(&off))
                .unwrap()
                .lights
                .is_empty()
        );
        assert!(
            live.frame(None, None, None).is_none(),
            "no depth, no surface"
        );
    }

    #[test]
    fn the_shadow_proxy_is_decimated_and_held_while_the_depth_stage_says_so() {
        let (depth, mut live) = flat_wall();
        let first = live.frame(Some(&depth), None, None).unwrap();
        let proxy = first.shadow_proxy.clone().unwrap();
        assert_eq!(
            first.meshes[0].triangles.len(),
            2 * 7 * 5,
            "the camera sees it all"
        );
        assert_eq!(proxy.triangles.len(), 2, "a flat wall is one quad");
        live.hold_surface();
        let held = live.frame(Some(&depth), None, None).unwrap();
        assert!(Arc::ptr_eq(&proxy, held.shadow_proxy.as_ref().unwrap()));
        let rebuilt = live.frame(Some(&depth), None, None).unwrap();
        assert!(
            !Arc::ptr_eq(&proxy, rebuilt.shadow_proxy.as_ref().unwrap()),
            "held one frame only"
        );
        assert_eq!(live.shadow_proxies_built(), 2);
    }

    #[test]
    fn holes_nan_and_depth_edges_make_no_triangles() {
        let mut depth = Image::new(8, 6, PixelFormat::DepthF32M);
        let d = depth.as_f32_mut().unwrap();
        d.fill(2.0);
        d[9] = 0.0;
        d[10] = f32::NAN;
        for row in 0..6 {
            d[row * 8 + 6] = 3.0;
            d[row * 8 + 7] = 3.0;
        }
        let mesh = depth_mesh(&depth, &camera(), &Pose::IDENTITY, 0, 1);
        assert!(mesh.positions_in_world.iter().all(|p| p.is_finite()));
        for tri in &mesh.triangles {
            let zs = tri.map(|k| mesh.positions_in_world[k as usize].z);
            assert!(
                zs.iter().all(|z| *z == zs[0]),
                "a triangle spans the depth edge: {zs:?}"
            );
        }
        assert!(mesh.triangles.len() < 2 * 7 * 5);
        assert!(!mesh.triangles.is_empty());
    }
}
