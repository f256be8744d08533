//! The volume around the virtual object that DLPV and DVCT both inject into: its placement, the
//! injection uniform (`Volume` in `shaders/common.wgsl`), the fixed-point scale that keeps the
//! integer atomics from overflowing, and timed compute passes.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use relight_core::scene::Scene;

use crate::deferred::RealIndirect;
use crate::engine::SceneFrame;
use crate::gbuffer::Targets;
use crate::gpu::{GpuContext, GpuError};
use crate::gpu_scene::GpuLight;
use crate::params::ParamSpec;
use crate::roofline::Work;
use crate::shaders;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct VolumeUniform {
    pub origin: [f32; 4],
    pub dims: [u32; 4],
    pub scale: [f32; 4],
    pub options: [u32; 4],
    pub object: [[f32; 4]; 3],
}

/// The virtual object as the real surfaces around it see it (`ObjectBox` in
/// `shaders/common.wgsl`, `blocked_irradiance`): its bounding box, its surface's area over the
/// box's, at most 1 (by Cauchy's formula a convex body's mean projected area is a quarter of its
/// surface's, so the box's projected area times that share is, on average over directions, the
/// object's), and its area-weighted diffuse albedo. Zeros without an object: then nothing is
/// blocked.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct ObjectBox {
    pub centre: Vec3,
    pub half: Vec3,
    pub area_share: f32,
    pub albedo: Vec3,
}

impl ObjectBox {
    pub fn of(scene: &Scene) -> Self {
        let Some((lo, hi)) = scene.virtual_bounds() else {
            return Self::default();
        };
        let (mut area, mut albedo) = (0.0, Vec3::ZERO);
        for m in scene.meshes.iter().filter(|m| m.is_virtual) {
            let material = scene
                .materials
                .get(m.material)
                .map_or(Vec3::ZERO, |m| m.albedo);
            for t in &m.triangles {
                let [a, b, c] = t.map(|i| m.positions_in_world[i as usize]);
                let triangle = 0.5 * (b - a).cross(c - a).length();
                area += triangle;
                albedo += triangle * material;
            }
        }
        let e = hi - lo;
        let box_area = 2.0 * (e.x * e.y + e.y * e.z + e.z * e.x);
        if box_area <= 0.0 || area <= 0.0 || !area.is_finite() {
            return Self::default();
        }
        Self {
            centre: 0.5 * (lo + hi),
            half: 0.5 * e,
            area_share: (area / box_area).min(1.0),
            albedo: albedo / area,
        }
    }

    /// `frame`'s object, zeros without a scene.
    pub fn of_frame(frame: &SceneFrame) -> Self {
        frame
            .scene
            .as_ref()
            .map_or_else(Self::default, |scene| Self::of(scene))
    }

    /// As the shaders' `ObjectBox`.
    pub fn uniform(&self) -> [[f32; 4]; 3] {
        [
            self.centre.extend(self.area_share).to_array(),
            self.half.extend(0.0).to_array(),
            self.albedo.extend(0.0).to_array(),
        ]
    }
}

/// The volume of `n`³ cells around `scene`'s virtual object, `None` without one: (minimum
/// corner, cell edge). A cube `scale` × the object's largest edge on a side, centred on the
/// object; then, `in_scene`, moved along each axis by as little as makes it cover as much of
/// the scene's bounds as it can while it still holds the whole object
/// (`volume_placement`, [`volume_placement_param`]). The bounds are the light-space geometry's
/// ([`Scene::light_space_bounds`]), which the volume's light comes from, and which a live
/// scene holds while its surface does: bounds that followed the sensor's noise moved the
/// volume every frame, and `dlpv` propagated again on every live frame (render 14 → 54 ms).
///
/// Why: an object on a floor or against a wall left the half of a centred cube below the floor
/// or behind the wall empty, cells that no surface, VPL or pixel can occupy, while the room's
/// light that the object blocks was cut off at the cube's other faces. Moved, the cube covers
/// at least as much of the scene's bounds, on touching_wall (a box in the corner of a floor
/// and a wall) 2.3 times as much. Where the centred cube already spans the scene along an
/// axis (an object on an open floor, in height) it stays: the cells' phase against the
/// surfaces alone moves the volume engines' object errors by a few hundredths.
pub(crate) fn placement(scene: &Scene, n: u32, scale: f32, in_scene: bool) -> Option<(Vec3, f32)> {
    let (lo, hi) = scene.virtual_bounds()?;
    let (scene_lo, scene_hi) = scene.light_space_bounds()?;
    let edge = (hi - lo).max_element().max(1e-3) * scale;
    let corner = Vec3::from_array(std::array::from_fn(|axis| {
        let centred = (lo[axis] + hi[axis] - edge) / 2.0;
        let (a, b) = (scene_lo[axis], scene_hi[axis] - edge);
        // (`clamp` panics on a NaN bound: a non-finite box keeps the centred cube.)
        let finite = [a, b, lo[axis], hi[axis], edge]
            .iter()
            .all(|v| v.is_finite());
        if !in_scene || !finite || edge < hi[axis] - lo[axis] {
            return centred;
        }
        // The corners that cover the most of the scene's extent: within it where the cube is
        // the shorter, around it where the scene is.
        let covering = centred.clamp(a.min(b), a.max(b));
        covering.clamp(hi[axis] - edge, lo[axis])
    }));
    Some((corner, edge / n as f32))
}

/// [`placement`] of `frame`'s scene: `None` without a scene or an object.
pub(crate) fn frame_placement(
    frame: &SceneFrame,
    n: u32,
    scale: f32,
    in_scene: bool,
) -> Option<(Vec3, f32)> {
    frame
        .scene
        .as_ref()
        .and_then(|s| placement(s, n, scale, in_scene))
}

/// Where a volume engine's indirect term can be nonzero on real pixels: within its volume of
/// `n`³ cells (`volume`, [`frame_placement`]) grown by `grow_cells` cells, and `margin_px`
/// pixels around where that is seen; anywhere without one.
pub(crate) fn volume_reach(
    volume: Option<(Vec3, f32)>,
    n: u32,
    grow_cells: f32,
    margin_px: u32,
) -> RealIndirect {
    volume.map_or(RealIndirect::Anywhere, |(origin, cell)| {
        let grow = Vec3::splat(grow_cells * cell);
        let far = origin + Vec3::splat(n as f32 * cell);
        RealIndirect::Within {
            bounds: (origin - grow, far + grow),
            margin_px,
        }
    })
}

/// Fixed-point counts per unit for injection: 2³⁰ over a bound on any single injected SH
/// coefficient's magnitude summed over a frame, which is every light's total flux (4π I for
/// point and spot lights, E · (2R)² for directional ones over the scene's bounding sphere of
/// radius `scene_radius`), twice (direct and indirect), twice (ρ and μ), times the cosine
/// lobe's largest coefficient over π.
pub(crate) fn fixed_point_scale(lights: &[GpuLight], scene_radius: f32) -> f32 {
    let total: f32 = lights
        .iter()
        .map(|l| {
            let peak = l.intensity[0]
                .max(l.intensity[1])
                .max(l.intensity[2])
                .max(0.0);
            if l.position[3] as u32 == 2 {
                peak * (2.0 * scene_radius).powi(2)
            } else {
                peak * 4.0 * std::f32::consts::PI
            }
        })
        .sum();
    let bound = total * 4.0 * 1.0234 / std::f32::consts::PI;
    if bound > 0.0 && bound.is_finite() {
        (1u64 << 30) as f32 / bound
    } else {
        1.0
    }
}

/// The `far_field` setting both volume engines have: `probe` (default) lights the object with
/// [`CellCounts::far_field`] as well as the volume, `none` with the volume alone (the papers).
pub(crate) fn far_field_param() -> ParamSpec {
    ParamSpec::choice(
        "far_field",
        "`probe`: the object also takes the light of real surfaces outside the volume, gathered at its centre as L2 SH (a volume reaches only `volume_scale` × the object); `none`: the volume's light alone, as in the paper",
        vec!["probe", "none"],
    )
}

/// The `volume_placement` setting both volume engines have: `scene` (default) moves the cube
/// out of what lies beyond the scene's bounds ([`placement`]), `centred` centres it on the
/// object (the papers).
pub(crate) fn volume_placement_param() -> ParamSpec {
    ParamSpec::choice(
        "volume_placement",
        "`scene`: the volume, centred on the object, is moved out of what lies beyond the scene's bounds (below a floor, behind a wall) as far as it still holds the object; `centred`: centred on the object, as in the paper",
        vec!["scene", "centred"],
    )
}

/// The injection's fixed-point counts, n³ cells × 12 (4 SH × RGB) i32 each of V^Δ and V^ρ, in
/// one buffer whose halves are bound apart: each half need only fit the adapter's largest
/// storage binding (lavapipe's 128 MiB held both only up to 110³). After them, the far field's
/// 27 sums ([`CellCounts::far_field`]), then the probe's ([`CellCounts::probe`]).
#[derive(Debug)]
pub(crate) struct CellCounts {
    pub buffer: wgpu::Buffer,
    /// One volume's bytes, what each binding holds (and what was checked against the limit).
    bytes: u64,
    /// Bytes from V^Δ's start to V^ρ's: one volume's, rounded up to the binding alignment.
    half: u64,
    /// Bytes from the far field's start to the probe's: the far field's, likewise rounded up.
    far: u64,
}

/// The far field's bytes: 9 L2 SH coefficients × RGB, i32 (`FAR_FIELD_VALUES` in common.wgsl).
const FAR_FIELD_BYTES: u64 = 27 * 4;

impl CellCounts {
    pub fn new(ctx: &GpuContext, label: &str, n: u32, setting: &str) -> Result<Self, GpuError> {
        let bytes = u64::from(n).pow(3) * 48;
        let alignment = u64::from(ctx.limits.min_storage_buffer_offset_alignment);
        let (half, far) = (
            bytes.next_multiple_of(alignment),
            FAR_FIELD_BYTES.next_multiple_of(alignment),
        );
        let size = 2 * half + far + FAR_FIELD_BYTES;
        ctx.require("max_storage_buffer_binding_size", bytes, setting)?;
        ctx.require("max_buffer_size", size, setting)?;
        Ok(Self {
            buffer: ctx.buffer(
                label,
                size,
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            ),
            bytes,
            half,
            far,
        })
    }

    /// V^Δ's counts (`which` 0) or V^ρ's (1).
    pub fn binding(&self, which: u64) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.buffer,
            offset: which * self.half,
            size: wgpu::BufferSize::new(self.bytes),
        })
    }

    /// The far field: the light of R^ρ's VPLs that land outside the volume, gathered at its
    /// centre as L2 SH of incident radiance (`dlpv_inject.wgsl`). A volume only reaches
    /// `volume_scale` × the object's size, so without it the object sees none of the room's
    /// bounce light (on desk_box 30–40 % of its radiance); the object's pixels add it
    /// (`dlpv_lookup.wgsl`, `dvct_trace.wgsl`).
    pub fn far_field(&self) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.buffer,
            offset: 2 * self.half,
            size: wgpu::BufferSize::new(FAR_FIELD_BYTES),
        })
    }

    /// The probe: the real scene's first bounce (every VPL of R^μ) arriving at the object's
    /// centre, as if the object were not there, as L2 SH of incident radiance (27 sums, as the
    /// far field's; `dlpv_inject.wgsl`, gathered with `options.y`). What the object blocks from
    /// the real surfaces around it (`blocked_irradiance` in `shaders/common.wgsl`).
    pub fn probe(&self) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.buffer,
            offset: 2 * self.half + self.far,
            size: wgpu::BufferSize::new(FAR_FIELD_BYTES),
        })
    }
}

/// The VPL injection pass (`dlpv_inject.wgsl`) both volume engines run: every R^ρ and R^μ
/// texel into fixed-point L1 SH cells (DLPV with direct injection on, DVCT's split injection
/// with it off).
#[derive(Debug)]
pub(crate) struct InjectPass {
    pipeline: wgpu::ComputePipeline,
}

impl InjectPass {
    pub fn new(device: &wgpu::Device, label: &str) -> Self {
        Self {
            pipeline: shaders::compute_pipeline(device, label, shaders::DLPV_INJECT),
        }
    }

    /// Bind the injection uniform, the light and face buffers, both maps and the cells.
    pub fn bind_group(
        &self,
        device: &wgpu::Device,
        uniform: &wgpu::Buffer,
        (lights, faces, rsm_rho, rsm_mu): (&wgpu::Buffer, &wgpu::Buffer, &Targets, &Targets),
        cells: &CellCounts,
    ) -> wgpu::BindGroup {
        let rsm_views = Targets::rsm_views(rsm_rho, rsm_mu);
        let mut resources = vec![
            uniform.as_entire_binding(),
            lights.as_entire_binding(),
            faces.as_entire_binding(),
        ];
        resources.extend(rsm_views.iter().map(wgpu::BindingResource::TextureView));
        resources.extend([
            cells.binding(0),
            cells.binding(1),
            cells.far_field(),
            cells.probe(),
        ]);
        shaders::pipeline_bind_group(device, &self.pipeline, "inject", &resources)
    }

    /// What injecting `layers` faces of `rsm_size`² into `cells` cells must do: every texel of
    /// R^ρ read once (32 bytes; R^μ only where the object covers it, a share this neglects), at
    /// least R^ρ's VPL turned into 12 fixed-point SH values (about 36 operations, 60 more for
    /// the texel's VPL itself; the V^Δ pairs that cancel need none), and the cells written once
    /// (48 bytes).
    pub fn work(rsm_size: u32, layers: u32, cells: f64) -> Work {
        let pairs = f64::from(layers) * f64::from(rsm_size).powi(2);
        Work::new(32.0, 156.0).times(pairs) + Work::new(48.0, 0.0).times(cells)
    }

    /// Inject every texel of `layers` shadow-map layers of `rsm_size`², both maps.
    pub fn dispatch(
        &self,
        pass: &mut wgpu::ComputePass,
        group: &wgpu::BindGroup,
        rsm_size: u32,
        layers: u32,
    ) {
        if layers == 0 {
            return;
        }
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, group, &[]);
        // Each thread injects a 4 × 4 tile (`TILE` in the shader), 8 × 8 threads a group.
        let s = rsm_size.div_ceil(4 * 8);
        pass.dispatch_workgroups(s, s, layers);
    }
}

/// `dvct`'s `far_receivers` setting: `emitters` (default) lights the real surfaces outside the
/// volume with [`FarEmitters`] (and the light the object blocks), `none` leaves them their
/// direct Δ alone (the paper). (`dlpv`'s real pixels lit by V^Δ's blocks as patches everywhere
/// were measured: `docs/ALGORITHMS.md`, `dlpv`.)
pub(crate) fn far_receivers_param() -> ParamSpec {
    ParamSpec::choice(
        "far_receivers",
        "`emitters`: real surfaces outside the volume take the Δ bounce of what the volume holds (the object's light and the light it takes from the real surfaces), summed into 8³ point emitters, and lose the light the object blocks; `none`: only surfaces within the volume get a bounce, as in the paper",
        vec!["emitters", "none"],
    )
}

/// Blocks per axis and their count (`FAR_EMITTER_BLOCKS`, `FAR_EMITTERS` in common.wgsl): 4
/// cells each at `dvct`'s 32³, 2 at `dlpv`'s 16³. For `dlpv`'s object, one a cell (16 per
/// axis) read the bench's object errors within 0.021 of these, closer on two scenes and farther
/// on three, and its still frames took 2.3–2.7 times as long (`docs/ALGORITHMS.md`, `dlpv`).
const FAR_EMITTER_BLOCKS: u32 = 8;
const FAR_EMITTERS: u64 = 512;

/// One emitter's bytes (`FarEmitter`: position, normal, intensity).
const FAR_EMITTER_BYTES: u64 = 48;

/// A volume's injected light as emitters (`shaders/far_emitters.wgsl`): its counts summed over
/// 8³ blocks of cells, each block's VPLs' summed lobes read as one clamped cosine lobe at their
/// cells' centre, the non-empty ones listed first. `dvct`'s far receivers take V^Δ's as points; `dlpv`'s object
/// takes V^ρ's as patches of surface (`patch_irradiance` in `shaders/common.wgsl`).
///
/// Why, for the far receivers: a volume spans `volume_scale` × the object, so a real pixel
/// beyond it had no bounce term, yet what the object changes in the room's first bounce reaches
/// every surface that sees it. On desk_box (a box under a lamp in a three-walled room) 92 % of
/// the real pixels lie
/// outside `dvct`'s volume, and the reference's one-bounce Δ there sums to −37 (in luminance,
/// against −8 inside), and held 61 % of stop 48's `dvct`'s squared error. Part of it is these
/// emitters' light (the floor the box shadows no longer lights the back wall, more than the
/// box's own top makes up for), more of it the lit floor the box now hides from the wall, which
/// `blocked_irradiance` (`shaders/common.wgsl`) adds beside them. Seen from outside, the volume's
/// contents are far enough away that a block of cells is one point (a cluster of lights seen
/// from afar as one, as in Walter et al.'s Lightcuts); its SH lobe is the sum of its VPLs'
/// cosine lobes, in which V^ρ's and V^μ's VPLs of one surface cancel as they do in the cells,
/// read back as one clamped cosine lobe (`far_emitter_irradiance`). No visibility: the light
/// between a receiver and the object is not in the volume.
#[derive(Debug)]
pub(crate) struct FarEmitters {
    pub buffer: wgpu::Buffer,
    sum: wgpu::ComputePipeline,
    list: wgpu::ComputePipeline,
}

impl FarEmitters {
    pub fn new(ctx: &GpuContext) -> Self {
        let source = shaders::FAR_EMITTERS;
        Self {
            // The listed count (16 bytes), then the emitters.
            buffer: ctx.buffer(
                "far emitters",
                16 + FAR_EMITTERS * FAR_EMITTER_BYTES,
                wgpu::BufferUsages::STORAGE,
            ),
            sum: shaders::compute_pipeline(&ctx.device, "far emitters", source),
            list: shaders::compute_pipeline_at(&ctx.device, "far emitters list", source, "list"),
        }
    }

    /// Sum `cells`' V^Δ (`which` 0) or V^ρ (1) into the emitters, the volume's placement and
    /// fixed-point scale read from `uniform` (`VolumeUniform`).
    pub fn dispatch(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass,
        uniform: &wgpu::Buffer,
        cells: &CellCounts,
        which: u64,
    ) {
        let resources = [
            uniform.as_entire_binding(),
            cells.binding(which),
            self.buffer.as_entire_binding(),
        ];
        let sum = shaders::pipeline_bind_group(device, &self.sum, "far emitters", &resources);
        let list = shaders::pipeline_bind_group_of(
            device,
            &self.list,
            "far emitters list",
            &resources,
            &[2],
        );
        pass.set_pipeline(&self.sum);
        pass.set_bind_group(0, &sum, &[]);
        pass.dispatch_workgroups((FAR_EMITTERS as u32).div_ceil(64), 1, 1);
        pass.set_pipeline(&self.list);
        pass.set_bind_group(0, &list, &[]);
        pass.dispatch_workgroups(1, 1, 1);
    }

    /// What summing `n`³ cells and listing the blocks must do: every cell's 12 counts read once
    /// (about 20 operations each), each emitter written and moved once.
    pub fn work(n: u32) -> Work {
        Work::new(48.0, 20.0).times(f64::from(n).powi(3))
            + Work::new(3.0 * FAR_EMITTER_BYTES as f64, 8.0).times(FAR_EMITTERS as f64)
    }
}

const _: () = assert!(FAR_EMITTERS == (FAR_EMITTER_BLOCKS as u64).pow(3));

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;
    use relight_core::scene::Mesh;

    use crate::test_scene as scene;

    /// desk_box's object is a box: its bounding box is itself, so its surface is all of the
    /// box's (share 1), and its albedo its material's. A scene without one blocks nothing.
    #[test]
    fn a_box_object_is_its_own_box() {
        let desk = scene("desk_box");
        let object = ObjectBox::of(&desk);
        let (lo, hi) = desk.virtual_bounds().unwrap();
        assert!((object.centre - 0.5 * (lo + hi)).length() < 1e-6);
        assert!((object.half - 0.5 * (hi - lo)).length() < 1e-6);
        assert!(
            (object.area_share - 1.0).abs() < 1e-5,
            "{}",
            object.area_share
        );
        let material = desk
            .meshes
            .iter()
            .find(|m| m.is_virtual)
            .map(|m| desk.materials[m.material].albedo)
            .unwrap();
        assert!((object.albedo - material).length() < 1e-5);
        assert_eq!(ObjectBox::of(&desk.without_virtual()), ObjectBox::default());
        assert_eq!(
            ObjectBox::default().uniform()[0][3],
            0.0,
            "no share, nothing blocked"
        );
    }

    /// The part of box `a` inside box `b`, as a volume (m³).
    fn overlap(a: (Vec3, Vec3), b: (Vec3, Vec3)) -> f32 {
        (a.1.min(b.1) - a.0.max(b.0))
            .max(Vec3::ZERO)
            .element_product()
    }

    /// On touching_wall (a box standing on the floor against the back wall) the cube moves up
    /// out of the floor and forward out of the wall; on an open floor, which the centred cube
    /// spans in height, it stays. On every scene it still holds the whole object, keeps its
    /// size, and covers at least as much of the scene's bounds as the cube centred on the
    /// object.
    #[test]
    fn the_volume_moves_out_of_empty_space_and_keeps_the_object() {
        let (n, scale) = (32, 3.0);
        for name in [
            "desk_box",
            "glossy_floor",
            "spot_bleed",
            "touching_wall",
            "window_env",
        ] {
            let scene = scene(name);
            let (lo, hi) = scene.virtual_bounds().unwrap();
            let bounds = scene.light_space_bounds().unwrap();
            let edge = (hi - lo).max_element() * scale;
            let (origin, cell) = placement(&scene, n, scale, true).unwrap();
            let placed = (origin, origin + Vec3::splat(n as f32 * cell));
            let centred = (
                (lo + hi - Vec3::splat(edge)) / 2.0,
                (lo + hi + Vec3::splat(edge)) / 2.0,
            );
            assert!((cell * n as f32 - edge).abs() < 1e-5, "{name}: size");
            assert!(
                placed.0.cmple(lo + 1e-5).all() && placed.1.cmpge(hi - 1e-5).all(),
                "{name}: the object is inside {placed:?}"
            );
            assert!(
                overlap(placed, bounds) >= overlap(centred, bounds) - 1e-6,
                "{name}: covers less of the scene than the centred cube"
            );
            if ["glossy_floor", "spot_bleed", "window_env"].contains(&name) {
                assert!(
                    (placed.0 - centred.0).abs().max_element() < 1e-5,
                    "{name}: an object on an open floor keeps the centred cube"
                );
            }
            if name == "touching_wall" {
                let eps = 1e-5;
                assert!(
                    (placed.0.y - bounds.0.y).abs() < eps,
                    "on the floor: {placed:?}"
                );
                assert!(
                    (placed.0.z - bounds.0.z).abs() < eps,
                    "at the wall: {placed:?}"
                );
                assert!(
                    overlap(placed, bounds) > 2.0 * overlap(centred, bounds),
                    "the wall's corner is where the centred cube lost most"
                );
            }
        }
    }

    /// A live scene's volume follows its held shadow proxy, not the depth surface, whose
    /// bounds move with the sensor's noise every frame: a volume that moves with them is
    /// propagated or injected again on every frame.
    #[test]
    fn a_held_proxy_holds_the_volume() {
        let mut scene = scene("touching_wall");
        let proxy = scene.meshes.iter().find(|m| !m.is_virtual).unwrap().clone();
        let held = placement(&scene, 32, 3.0, true);
        scene.shadow_proxy = Some(std::sync::Arc::new(Mesh {
            positions_in_world: scene
                .meshes
                .iter()
                .filter(|m| !m.is_virtual)
                .flat_map(|m| m.positions_in_world.iter().copied())
                .collect(),
            ..proxy
        }));
        for noise in [-0.004, 0.003] {
            for mesh in scene.meshes.iter_mut().filter(|m| !m.is_virtual) {
                for p in &mut mesh.positions_in_world {
                    *p += Vec3::splat(noise);
                }
            }
            assert_eq!(placement(&scene, 32, 3.0, true), held, "noise {noise}");
        }
    }

    /// An object floating in the middle of a large scene keeps the centred cube; on a floor
    /// under a high room it sits on the floor; where the centred cube spans the scene's
    /// height, it stays; unbounded geometry leaves it centred.
    #[test]
    fn the_volume_is_centred_where_nothing_bounds_it() {
        let mut scene = scene("desk_box");
        let (lo, hi) = scene.virtual_bounds().unwrap();
        let centre = (lo + hi) / 2.0;
        let big = 100.0 * (hi - lo).max_element();
        let edge = (hi - lo).max_element() * 3.0;
        let set_real = |scene: &mut Scene, a: Vec3, b: Vec3| {
            for mesh in scene.meshes.iter_mut().filter(|m| !m.is_virtual) {
                mesh.positions_in_world = vec![a, b];
                mesh.triangles.clear();
            }
        };
        set_real(
            &mut scene,
            centre - Vec3::splat(big),
            centre + Vec3::splat(big),
        );
        let (origin, _) = placement(&scene, 16, 3.0, true).unwrap();
        assert!((origin + Vec3::splat(edge / 2.0) - centre).length() < 1e-4 * edge);

        // A floor under the object and the room's walls far off: the cube sits on the floor,
        // centred on the object in x and z.
        let floor = lo.y - 1e-3;
        set_real(
            &mut scene,
            Vec3::new(centre.x - big, floor, centre.z - big),
            Vec3::new(centre.x + big, floor + big, centre.z + big),
        );
        let (origin, _) = placement(&scene, 16, 3.0, true).unwrap();
        assert!((origin.y - floor).abs() < 1e-5, "{origin}");
        assert!((origin.x + edge / 2.0 - centre.x).abs() < 1e-5, "{origin}");
        // A scene lower than the cube (a floor as wide as the room, nothing above the object):
        // the centred cube spans it already, and stays.
        set_real(
            &mut scene,
            Vec3::new(centre.x - big, floor, centre.z - big),
            Vec3::new(centre.x + big, floor, centre.z + big),
        );
        let (origin, _) = placement(&scene, 16, 3.0, true).unwrap();
        assert!((origin.y + edge / 2.0 - centre.y).abs() < 1e-5, "{origin}");
        // Unbounded real geometry keeps the centred cube rather than failing.
        set_real(
            &mut scene,
            Vec3::splat(f32::NEG_INFINITY),
            Vec3::splat(f32::INFINITY),
        );
        let (origin, _) = placement(&scene, 16, 3.0, true).unwrap();
        assert!((origin + Vec3::splat(edge / 2.0) - centre).length() < 1e-4 * edge);
        assert!((origin.z + edge / 2.0 - centre.z).abs() < 1e-5, "{origin}");
    }

    /// `patch_irradiance` (`shaders/common.wgsl`) against the integral it stands for, summed
    /// over 600² pieces of the square in f64: a Lambertian square of half edge 1 and unit
    /// intensity along its normal (+y), seen head on, from beside its edge low down (a face
    /// standing on a lit floor), from a receiver whose horizon cuts it, from behind it, and from
    /// past `PATCH_AS_POINT` half edges, where it is taken as a point (within 4 % of the
    /// head-on light at that distance).
    #[test]
    fn a_patch_gives_its_contour_integral() {
        let cases: [(DVec3, DVec3, f64); 6] = [
            (DVec3::new(0.0, 1.0, 0.0), DVec3::NEG_Y, 0.01),
            (DVec3::new(1.05, 0.1, 0.3), DVec3::NEG_X, 0.01),
            (DVec3::new(0.5, 0.4, 0.0), DVec3::new(-1.0, -0.3, 0.0), 0.01),
            (DVec3::new(-0.3, 0.5, 0.2), DVec3::new(0.2, -1.0, 0.4), 0.01),
            (DVec3::new(0.2, -0.5, 0.0), DVec3::Y, 0.0),
            (
                DVec3::new(5.0, 4.0, 2.0),
                DVec3::new(-1.0, -0.5, -0.2),
                0.04,
            ),
        ];
        // A cosine lobe of unit intensity about +y.
        let emitter: Vec<f32> = [[0.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 0.0], [1.0; 4]].concat();
        let queries: Vec<f32> = cases
            .iter()
            .flat_map(|(p, n, _)| {
                let n = n.normalize();
                [p.x, p.y, p.z, 0.0, n.x, n.y, n.z, 0.0].map(|v| v as f32)
            })
            .collect();
        let gpu = shaders::evaluate(
            "@group(0) @binding(0) var<storage, read> emitter: FarEmitter;
            @group(0) @binding(1) var<storage, read> queries: array<vec4<f32>>;
            @group(0) @binding(2) var<storage, read_write> result: array<f32>;
            @compute @workgroup_size(1)
            fn main(@builtin(global_invocation_id) id: vec3<u32>) {
                let p = queries[2u * id.x].xyz;
                let n = queries[2u * id.x + 1u].xyz;
                result[id.x] = patch_irradiance(emitter, 0.0, p, n).x;
            }",
            &emitter,
            &queries,
            cases.len(),
        );
        // Radiance intensity / area = 1/4 over the square x, z ∈ [−1, 1] at y = 0.
        let square = (
            DVec3::new(-1.0, 0.0, -1.0),
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(0.0, 0.0, 2.0),
            DVec3::Y,
        );
        for ((p, n, tolerance), gpu) in cases.iter().zip(&gpu) {
            let n = n.normalize();
            let expected = 0.25 * shaders::rectangle_form_factor((*p, n), square, 600);
            let head_on = 0.25 * 4.0 / p.length_squared();
            eprintln!("at {p} facing {n}: {gpu:.5}, the integral {expected:.5}");
            assert!(
                (f64::from(*gpu) - expected).abs() <= tolerance * head_on.max(expected) + 1e-6,
                "at {p} facing {n}: {gpu} against {expected}"
            );
        }
    }
}
