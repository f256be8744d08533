//! Measured albedo of the depth-derived real surface: DLPV's eq. 1 estimator
//! ([`relight_recon::albedo`], Franke 2013) run on the live mesh's own sample grid, with the
//! lights the engines are lit by, and its running mean carried onto every vertex of the mesh.
//!
//! The estimator works on the grid of depth samples the mesh is built from (every `stride`-th
//! pixel, [`DepthGrid`]), so each vertex has exactly one estimate and nothing is resampled:
//! its point and normal are the vertex's, its colour the colour camera's pixel there (depth is
//! registered to colour). The room's own bounce light, as the colour camera sees it on the same
//! grid ([`relight_recon::bounce`]), is added to the lights' irradiance. Shadowed pixels are
//! found by shadow rays against the same mesh
//! at a coarser sampling (the reference renderer's BVH, [`relight_reference::accel::Geometry`],
//! over ≈ 5000 triangles: rebuilt every estimate, it cost 52 ms over the full 38 k-triangle
//! mesh at 160 × 120 cells and costs 1.5 ms so); the virtual object casts no real shadow and is
//! left out. A ray starts [`SHADOW_RAY_OFFSET_M`] along the normal,
//! above the depth noise, so a bumpy surface does not shadow itself.
//!
//! With `every` > 1 the estimate runs on every `every`-th frame only; the frames between take
//! the last estimate through its view: each vertex is projected into that view and takes the
//! estimate of the cell it lands on when that cell saw the same surface (depth within
//! [`AlbedoSettings::max_depth_difference`]). A vertex with no estimate yet gets the configured
//! default albedo.
//!
//! The estimate runs inline by default, in frame order, so a replay's estimates do not depend on
//! thread timing (`relightd score`). [`SurfaceAlbedo::estimate_on_own_thread`] moves it to a
//! thread of its own (the daemon): a frame then hands its inputs over when the thread is idle
//! and takes whichever estimate is newest through the same view lookup, so the render thread
//! never waits for eq. 1 (about 80 % of the live scene stage, 20–30 ms a frame at 320 × 240), and
//! at the lowest CPU priority, so that it takes only the time the frame loop leaves.

use std::thread::JoinHandle;

use crossbeam_channel::{Receiver, Sender, TryRecvError, bounded};
use glam::Vec3;
use rayon::prelude::*;
use relight_core::camera::{Pinhole, optical_from_gl};
use relight_core::light::Light;
use relight_core::scene::Mesh;
use relight_core::{Image, PixelFormat, Pose};
use relight_recon::albedo::{
    AlbedoCensus, AlbedoError, AlbedoEstimator, AlbedoInput, AlbedoSettings, ColorDecoding,
    ShadowQuery,
};
use relight_recon::bounce::{BounceInput, bounce_irradiance};
use relight_recon::normals::{NormalMap, PositionMap};
use relight_reference::accel::Geometry;

/// Shadow rays start this far along the normal: a few times a Kinect-class sensor's depth noise
/// at desk range (≈ 3 mm at 1.5 m), so the merged surface's ripple does not occlude itself.
pub const SHADOW_RAY_OFFSET_M: f32 = 0.02;

/// About this many emitters (and receivers) in the bounce gather: its cost is their square
/// (≈ 5 ms at 600 on one core), while the bounce light varies slowly over a room.
const BOUNCE_PATCHES: usize = 600;

/// Which depth-grid cell each vertex of a depth mesh came from.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthGrid {
    /// Cells per row and column (the depth image's size divided by `stride`, rounded up).
    pub width: u32,
    pub height: u32,
    /// Depth pixels per cell along each axis.
    pub stride: u32,
    /// Per cell, row-major: the mesh vertex made from it (`None`: no valid depth there).
    pub vertex_of_cell: Vec<Option<u32>>,
}

impl DepthGrid {
    /// The pinhole that sees the grid's cells as its pixels ([`Pinhole::subsampled`] by
    /// `stride`: cell x is depth pixel `x · stride`), without distortion, as the mesh is
    /// triangulated.
    pub fn camera(&self, camera: &Pinhole) -> Pinhole {
        Pinhole {
            width: self.width,
            height: self.height,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
            ..camera.subsampled(self.stride)
        }
    }
}

/// The last estimate, in the view it was made from.
#[derive(Debug, Clone)]
struct View {
    camera_from_world: Pose,
    camera: Pinhole,
    /// Distance along the view axis per cell, 0 where there was no surface.
    depth_m: Vec<f32>,
    albedo: Vec<Option<Vec3>>,
}

/// What the last frame's albedo measurement did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct AlbedoReport {
    /// Whether the estimator ran on this frame (else the last estimate was carried over).
    pub estimated: bool,
    /// The estimator's census of this frame's cells (zero when it did not run).
    pub census: AlbedoCensus,
    /// Vertices that got a measured albedo, and all vertices.
    pub measured_vertices: usize,
    pub vertices: usize,
}

/// The live surface's albedo measurement; see the module docs.
#[derive(Debug)]
pub struct SurfaceAlbedo {
    estimation: Estimation,
    /// [`AlbedoSettings::max_depth_difference`]: how far a vertex may lie from the surface a
    /// view's cell saw and still take its estimate.
    tolerance: f32,
    default: Vec3,
    every: u32,
    frames: u64,
    last: Option<View>,
    report: AlbedoReport,
}

/// Eq. 1 with its running state (the estimator's mean per cell).
#[derive(Debug)]
struct Estimator {
    estimator: AlbedoEstimator,
}

/// Where estimates are made.
#[derive(Debug)]
enum Estimation {
    Inline(Box<Estimator>),
    Thread(EstimatorThread),
}

/// One estimate's inputs, owned, for the estimator's thread.
struct Job {
    mesh: Mesh,
    grid: DepthGrid,
    camera: Pinhole,
    world_from_camera: Pose,
    color: Image,
    lights: Vec<Light>,
}

/// The estimator on a thread of its own: one job at a time, its results back as they finish.
#[derive(Debug)]
struct EstimatorThread {
    jobs: Option<Sender<Job>>,
    results: Receiver<Result<(View, AlbedoCensus), AlbedoError>>,
    /// A job was handed over and its result has not come back.
    busy: bool,
    thread: Option<JoinHandle<()>>,
}

impl Drop for EstimatorThread {
    fn drop(&mut self) {
        // Closing the job channel ends the thread after the estimate it is making.
        self.jobs = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl SurfaceAlbedo {
    /// Colour codes decode through `decoding`; vertices without an estimate get `default`; the
    /// estimator runs on every `every`-th frame (≥ 1).
    pub fn new(
        settings: AlbedoSettings,
        decoding: ColorDecoding,
        default: Vec3,
        every: u32,
    ) -> Self {
        Self {
            tolerance: settings.max_depth_difference,
            estimation: Estimation::Inline(Box::new(Estimator {
                estimator: AlbedoEstimator::new(settings, decoding),
            })),
            default,
            every: every.max(1),
            frames: 0,
            last: None,
            report: AlbedoReport::default(),
        }
    }

    /// Make estimates on a thread of their own from now on (see the module docs).
    pub fn estimate_on_own_thread(&mut self) -> std::io::Result<()> {
        if let Estimation::Inline(_) = &self.estimation {
            let stopped = Estimation::Thread(EstimatorThread::stopped());
            let Estimation::Inline(estimator) = std::mem::replace(&mut self.estimation, stopped)
            else {
                unreachable!("matched above")
            };
            self.estimation = Estimation::Thread(EstimatorThread::spawn(estimator)?);
        }
        Ok(())
    }

    /// The colour camera's decoding from a rig calibration's `color_response` and
    /// `color_radiance_scale`.
    pub fn decoding(response: &[f32], radiance_scale: f32) -> Result<ColorDecoding, AlbedoError> {
        ColorDecoding::from_table(response, 1.0 / radiance_scale)
    }

    pub fn report(&self) -> AlbedoReport {
        self.report
    }

    /// Measure on this frame if due, then set `mesh.vertex_albedo` (a depth mesh built on `grid`
    /// by `camera` at `world_from_camera`, `color` the registered colour image, `lights` what
    /// the engines light the frame with).
    pub fn apply(
        &mut self,
        mesh: &mut Mesh,
        grid: &DepthGrid,
        camera: &Pinhole,
        world_from_camera: &Pose,
        color: Option<&Image>,
        lights: &[Light],
    ) {
        let due = self.frames.is_multiple_of(u64::from(self.every));
        self.frames += 1;
        self.report = AlbedoReport::default();
        let estimated = match &mut self.estimation {
            Estimation::Inline(estimator) => color.filter(|_| due).map(|color| {
                estimator.estimate(mesh, grid, camera, world_from_camera, color, lights)
            }),
            Estimation::Thread(thread) => {
                let finished = thread.take_result();
                // The inputs are copied (the mesh, its grid, the colour image) only when the
                // thread will take them.
                if due
                    && thread.idle()
                    && let Some(color) = color
                {
                    thread.offer(Job {
                        mesh: mesh.clone(),
                        grid: grid.clone(),
                        camera: *camera,
                        world_from_camera: *world_from_camera,
                        color: color.clone(),
                        lights: lights.to_vec(),
                    });
                }
                finished
            }
        };
        match estimated {
            Some(Ok((view, census))) => {
                self.last = Some(view);
                self.report.estimated = true;
                self.report.census = census;
            }
            Some(Err(error)) => tracing::debug!(%error, "albedo not estimated on this frame"),
            None => {}
        }
        let last = self.last.as_ref();
        let tolerance = self.tolerance;
        // A projection and a depth test per vertex, tens of thousands on the render thread's
        // path: spread over the cores.
        let mut albedo: Vec<Option<Vec3>> = mesh
            .positions_in_world
            .par_iter()
            .map(|p| last.and_then(|view| view.lookup(*p, tolerance)))
            .collect();
        self.report.measured_vertices = albedo.iter().flatten().count();
        fill_along_surfaces(&mut albedo, mesh, grid);
        mesh.vertex_albedo = albedo
            .into_iter()
            .map(|a| a.unwrap_or(self.default))
            .collect();
        self.report.vertices = mesh.positions_in_world.len();
    }
}

impl Estimator {
    /// Eq. 1 on `mesh` (built on `grid` by `camera` at `world_from_camera`), with `color`
    /// registered to it and `lights` lighting it: the estimate, in the view it was made from.
    fn estimate(
        &mut self,
        mesh: &Mesh,
        grid: &DepthGrid,
        camera: &Pinhole,
        world_from_camera: &Pose,
        color: &Image,
        lights: &[Light],
    ) -> Result<(View, AlbedoCensus), AlbedoError> {
        let grid_camera = grid.camera(camera);
        let camera_from_world = world_from_camera.inverse();
        let vertex_of = |cell: &Option<u32>| cell.map(|v| v as usize);
        let points_in_world: Vec<Option<Vec3>> = grid
            .vertex_of_cell
            .iter()
            .map(|cell| vertex_of(cell).and_then(|v| mesh.positions_in_world.get(v).copied()))
            .collect();
        let normals_in_world: Vec<Option<Vec3>> = grid
            .vertex_of_cell
            .iter()
            .map(|cell| {
                vertex_of(cell)
                    .and_then(|v| mesh.normals_in_world.get(v).copied())
                    .filter(|n| n.length_squared() > 0.5)
            })
            .collect();
        let positions = PositionMap {
            width: grid.width,
            height: grid.height,
            points_in_camera: points_in_world
                .iter()
                .map(|p| p.map(|p| camera_from_world.transform_point(p)))
                .collect(),
        };
        let normals = NormalMap {
            width: grid.width,
            height: grid.height,
            normals_in_camera: normals_in_world
                .iter()
                .map(|n| n.map(|n| camera_from_world.transform_vector(n)))
                .collect(),
        };
        let grid_color = sample_color(color, grid, camera)?;
        let indirect = self.bounce(
            &grid_color,
            &grid_camera,
            world_from_camera.translation,
            &points_in_world,
            &normals_in_world,
        );
        let occluders = Geometry::of_meshes(
            &[coarse_occluders(mesh, grid, world_from_camera.translation)],
            false,
        );
        let input = AlbedoInput {
            color: &grid_color,
            positions: &positions,
            normals: &normals,
            camera: &grid_camera,
            world_from_camera: *world_from_camera,
            lights,
            indirect_irradiance: &indirect,
        };
        let frame = self.estimator.estimate(&input, |query: &ShadowQuery| {
            let origin = query.point_in_world + query.normal_in_world * SHADOW_RAY_OFFSET_M;
            let t_max = if query.incident.distance_m.is_finite() {
                query.incident.distance_m - SHADOW_RAY_OFFSET_M
            } else {
                f32::INFINITY
            };
            let blocked = occluders
                .intersect(origin, query.incident.direction_to_light, 0.0, t_max)
                .is_some();
            if blocked { 0.0 } else { 1.0 }
        })?;
        let view = View {
            camera_from_world,
            camera: grid_camera,
            depth_m: positions
                .points_in_camera
                .iter()
                .map(|p| p.map_or(0.0, |p| -p.z))
                .collect(),
            albedo: frame.albedo,
        };
        Ok((view, frame.census))
    }

    /// The bounce light on every cell from the cells' measured radiance.
    fn bounce(
        &self,
        grid_color: &Image,
        grid_camera: &Pinhole,
        eye_in_world: Vec3,
        points_in_world: &[Option<Vec3>],
        normals_in_world: &[Option<Vec3>],
    ) -> Vec<Vec3> {
        let saturated = self.estimator.settings().saturated_code;
        let decoding = self.estimator.decoding();
        let radiance: Vec<Option<Vec3>> = grid_color
            .as_u8()
            .unwrap_or_default()
            .chunks_exact(3)
            .map(|c| {
                let codes = [c[0], c[1], c[2]];
                (codes.iter().all(|c| *c < saturated)).then(|| decoding.radiance(codes))
            })
            .collect();
        let cells = radiance.len();
        let step = ((cells as f64 / BOUNCE_PATCHES as f64).sqrt().ceil() as u32).max(1);
        bounce_irradiance(
            &BounceInput {
                camera: grid_camera,
                eye_in_world,
                points_in_world,
                normals_in_world,
                radiance: &radiance,
            },
            step,
        )
    }
}

/// The estimator thread's nice value. An estimate costs about 20 ms of CPU at 320 × 240, and
/// an idle thread takes each frame's inputs: at normal priority it estimated on 58-60 of the
/// bundled recording's 60 frames and slowed a live `differential` replay on two cores by 7 %
/// (2.30-2.39 s against 2.15-2.18 s at 19, which still estimated on 40-46). The running mean
/// needs no more than the spare CPU gives it.
const ESTIMATOR_NICE: i32 = 19;

impl EstimatorThread {
    /// `estimator` on a thread called `albedo`, at the lowest priority ([`ESTIMATOR_NICE`]).
    fn spawn(mut estimator: Box<Estimator>) -> std::io::Result<Self> {
        let (jobs, job_queue) = bounded::<Job>(1);
        let (result_queue, results) = bounded(1);
        let thread = std::thread::Builder::new()
            .name("albedo".into())
            .spawn(move || {
                // The lowest priority: the thread takes the CPU the frame loop leaves. On Linux
                // the nice value is the calling thread's. Refused (a sandbox), it runs as before.
                if let Err(error) = rustix::process::setpriority_process(None, ESTIMATOR_NICE) {
                    tracing::debug!(%error, "the albedo thread keeps its priority");
                }
                for job in job_queue {
                    let result = estimator.estimate(
                        &job.mesh,
                        &job.grid,
                        &job.camera,
                        &job.world_from_camera,
                        &job.color,
                        &job.lights,
                    );
                    if result_queue.send(result).is_err() {
                        break;
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(jobs),
            results,
            busy: false,
            thread: Some(thread),
        })
    }

    /// No thread: takes no job and gives no result.
    fn stopped() -> Self {
        Self {
            jobs: None,
            results: bounded(0).1,
            busy: false,
            thread: None,
        }
    }

    /// The estimate the thread finished since the last call, if any.
    fn take_result(&mut self) -> Option<Result<(View, AlbedoCensus), AlbedoError>> {
        match self.results.try_recv() {
            Ok(result) => {
                self.busy = false;
                Some(result)
            }
            Err(TryRecvError::Empty) => None,
            Err(TryRecvError::Disconnected) => {
                self.busy = false;
                None
            }
        }
    }

    /// Whether the thread would take a job: it is running and has none.
    fn idle(&self) -> bool {
        !self.busy && self.jobs.is_some()
    }

    /// Hand `job` to the thread (when [`Self::idle`]; a frame that finds it busy estimates
    /// nothing).
    fn offer(&mut self, job: Job) {
        if self.idle()
            && self
                .jobs
                .as_ref()
                .is_some_and(|jobs| jobs.try_send(job).is_ok())
        {
            self.busy = true;
        }
    }
}

impl View {
    /// The estimate of the cell `point_in_world` lands on, if that cell saw the same surface.
    fn lookup(&self, point_in_world: Vec3, tolerance: f32) -> Option<Vec3> {
        let p = self.camera_from_world.transform_point(point_in_world);
        let c = &self.camera;
        let pixel = c.project(optical_from_gl(p.as_dvec3()))?;
        let (x, y) = (pixel.x.round(), pixel.y.round());
        if x < 0.0 || y < 0.0 || x >= f64::from(c.width) || y >= f64::from(c.height) {
            return None;
        }
        let cell = y as usize * c.width as usize + x as usize;
        let seen = *self.depth_m.get(cell)?;
        let z = -p.z;
        let same_surface = seen > 0.0 && (seen - z).abs() <= tolerance * z;
        same_surface.then(|| self.albedo[cell]).flatten()
    }
}

/// About this many grid blocks in the shadow rays' occluder mesh: its BVH is rebuilt every
/// estimate, and a shadow needs the room's shape, not the depth mesh's every sample.
const OCCLUDER_BLOCKS: usize = 2500;

/// The depth surface at every `step`-th grid cell, triangulated as [`crate::live_scene`] does
/// (two triangles per block whose corners agree in depth within 5 %).
fn coarse_occluders(mesh: &Mesh, grid: &DepthGrid, eye_in_world: Vec3) -> Mesh {
    let (w, h) = (grid.width as usize, grid.height as usize);
    let step = ((w * h) as f64 / OCCLUDER_BLOCKS as f64)
        .sqrt()
        .ceil()
        .max(1.0) as usize;
    let vertex = |x: usize, y: usize| {
        let v = grid.vertex_of_cell.get(y * w + x).copied().flatten()?;
        mesh.positions_in_world.get(v as usize).map(|_| v)
    };
    let depth = |v: u32| (mesh.positions_in_world[v as usize] - eye_in_world).length();
    let joined = |a: u32, b: u32| {
        let (da, db) = (depth(a), depth(b));
        (da - db).abs() <= 0.05 * da.min(db)
    };
    let mut triangles = Vec::new();
    for y in (0..h.saturating_sub(step)).step_by(step) {
        for x in (0..w.saturating_sub(step)).step_by(step) {
            let corners = [
                vertex(x, y),
                vertex(x + step, y),
                vertex(x, y + step),
                vertex(x + step, y + step),
            ];
            for [a, b, c] in [[0, 2, 1], [1, 2, 3]] {
                if let (Some(a), Some(b), Some(c)) = (corners[a], corners[b], corners[c])
                    && joined(a, b)
                    && joined(b, c)
                    && joined(a, c)
                {
                    triangles.push([a, b, c]);
                }
            }
        }
    }
    Mesh {
        name: "occluders".into(),
        positions_in_world: mesh.positions_in_world.clone(),
        normals_in_world: Vec::new(),
        triangles,
        material: 0,
        is_virtual: false,
        vertex_albedo: Vec::new(),
    }
}

/// Cells of the grid a measured albedo spreads over, along a surface, to neighbours that have
/// none (in shadow, under a highlight): about 10 cm at desk range with the default stride.
const FILL_CELLS: usize = 8;

/// Give vertices without an estimate the mean of their grid neighbours' that lie on the same
/// surface (normals within ≈ 18°, points within 5 cm), growing one cell per pass: a shadow on a
/// floor takes the floor's albedo rather than the default.
fn fill_along_surfaces(albedo: &mut [Option<Vec3>], mesh: &Mesh, grid: &DepthGrid) {
    let (w, h) = (grid.width as usize, grid.height as usize);
    let vertices = albedo.len().min(mesh.normals_in_world.len());
    let vertex = |x: usize, y: usize| {
        let v = grid.vertex_of_cell.get(y * w + x).copied().flatten()? as usize;
        (v < vertices).then_some(v)
    };
    let same_surface = |a: usize, b: usize| {
        let (pa, pb) = (mesh.positions_in_world[a], mesh.positions_in_world[b]);
        let (na, nb) = (mesh.normals_in_world[a], mesh.normals_in_world[b]);
        na.dot(nb) > 0.95 && (pa - pb).length() < 0.05
    };
    for _ in 0..FILL_CELLS {
        let before = albedo.to_vec();
        let mut grew = false;
        for y in 0..h {
            for x in 0..w {
                let Some(v) = vertex(x, y) else { continue };
                if before[v].is_some() {
                    continue;
                }
                let neighbours = [
                    (x > 0).then(|| (x - 1, y)),
                    (x + 1 < w).then(|| (x + 1, y)),
                    (y > 0).then(|| (x, y - 1)),
                    (y + 1 < h).then(|| (x, y + 1)),
                ];
                let (sum, n) = neighbours
                    .into_iter()
                    .flatten()
                    .filter_map(|(nx, ny)| vertex(nx, ny))
                    .filter(|u| same_surface(v, *u))
                    .filter_map(|u| before[u])
                    .fold((Vec3::ZERO, 0u32), |(s, n), a| (s + a, n + 1));
                if n > 0 {
                    albedo[v] = Some(sum / n as f32);
                    grew = true;
                }
            }
        }
        if !grew {
            break;
        }
    }
}

/// The colour camera's codes at the grid's cells (nearest pixel; the colour image may be of
/// another size than the depth it is registered to).
fn sample_color(color: &Image, grid: &DepthGrid, camera: &Pinhole) -> Result<Image, AlbedoError> {
    let codes = match (color.format(), color.as_u8()) {
        (PixelFormat::Rgb8, Some(codes)) => codes,
        (format, _) => return Err(AlbedoError::ColorFormat { format }),
    };
    let scale_x = f64::from(color.width()) / f64::from(camera.width.max(1));
    let scale_y = f64::from(color.height()) / f64::from(camera.height.max(1));
    let mut out = Image::new(grid.width, grid.height, PixelFormat::Rgb8);
    let pixels = out.as_u8_mut().unwrap_or_default();
    for y in 0..grid.height {
        for x in 0..grid.width {
            let cx = (f64::from(x * grid.stride) * scale_x) as u32;
            let cy = (f64::from(y * grid.stride) * scale_y) as u32;
            let cx = cx.min(color.width().saturating_sub(1));
            let cy = cy.min(color.height().saturating_sub(1));
            let from = 3 * (cy as usize * color.width() as usize + cx as usize);
            let to = 3 * (y as usize * grid.width as usize + x as usize);
            if let (Some(src), Some(dst)) = (codes.get(from..from + 3), pixels.get_mut(to..to + 3))
            {
                dst.copy_from_slice(src);
            }
        }
    }
    Ok(out)
}
