//! The second bounce (Knecht et al. 2012, Sec. 4.3: "multiple bounces forward the path flag
//! x̄ = r(x̄_prev) r(p_VPL)"): VPLs where the first-bounce VPLs' light lands.
//!
//! Each second-bounce VPL continues a first-bounce VPL along a cosine-distributed direction (a
//! Lambertian emitter of flux Φ sends Φ/m along each of m such rays) to the surface it meets,
//! which reflects Φ/m · ρ(hit). The ray is traced twice, through the light-space geometry with
//! the object (the scene the VPL lights in L_rv) and without it (L_r), as the reference traces
//! ρ and μ along one path, so the path flag follows from where the two land:
//! - the same real surface in both: class 0, lighting both solutions (so Δ stays exactly 0
//!   wherever the object plays no part);
//! - elsewhere (the object is met, or it blocks the way): the landing with the object is a
//!   class-1 VPL (L_rv only), the landing without it a class-2 VPL (L_r only: the real
//!   second-bounce light the object now takes away);
//! - a first-bounce VPL of class 1 (on the object) continues in the scene with it only, one
//!   of class 2 in the real scene only.
//!
//! The rays the object changes are few (in a live frame of the desk, 5 of 256 cosine rays met
//! the box), so which of them do flickered: the bundled recording's live frames 4–6 read Δ
//! 0.61–0.65 where their neighbours read 0.27–0.42. So the directions are stratified
//! ([`second_bounce`]'s `object_rays`): the cosine rays keep only the landings the object
//! does not change, and rays aimed into the cone of the object's bounding sphere (the whole
//! hemisphere from inside it), sources chosen by the light they send there, give the ones it
//! does. The two parts partition each source's light (a ray the object changes passes through
//! its bounding sphere), so the sum is the same in expectation with far fewer rays left to
//! chance. The light landing on the object is then not taken from where those rays land but
//! from a grid of points on its box's faces, each lit by every source ([`object_face_vpls`]):
//! a real surface beside the object sees its nearest face over up to half its hemisphere, so a
//! single landing there showed.
//!
//! Why on the CPU: a few hundred rays a frame, against the reference's BVH
//! ([`relight_reference::accel`]), which the rasterising passes have no counterpart of (no ray
//! queries in the engines' WGSL); the first-bounce VPLs are read back for it (12 kB). Why it
//! matters, measured: the reference truncated at one bounce stays 0.22 and 0.28 (relative L2 of
//! Δ) from the full one on desk_box and touching_wall, at two within 0.10 and 0.13
//! (docs/ALGORITHMS.md, "What one bounce can reach").

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use relight_core::scene::{Mesh, Scene};
use relight_reference::accel::Geometry;

/// `Vpl` in `shaders/common.wgsl`: position (w: class 0, 1 or 2), normal, flux Φ (W).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct GpuVpl {
    pub position: [f32; 4],
    pub normal: [f32; 4],
    pub flux: [f32; 4],
}

impl GpuVpl {
    fn new(position: Vec3, normal: Vec3, flux: Vec3, class: u32, clamp_m: f32) -> Self {
        Self {
            position: position.extend(class as f32).to_array(),
            normal: normal.extend(clamp_m).to_array(),
            flux: flux.extend(0.0).to_array(),
        }
    }

    fn class(&self) -> u32 {
        self.position[3] as u32
    }

    fn flux(&self) -> Vec3 {
        Vec3::from_slice(&self.flux[..3])
    }

    fn position(&self) -> Vec3 {
        Vec3::from_slice(&self.position[..3])
    }

    /// The unit normal (zero where it has none).
    fn normal(&self) -> Vec3 {
        Vec3::from_slice(&self.normal[..3]).normalize_or_zero()
    }
}

/// The light-space geometry (what the shadow maps draw: the real scene's proxy where it has
/// one, and the object), the real part and the object in a BVH each (the scene with the object
/// is both: one real BVH to build, not two), and the materials' albedo.
#[derive(Debug)]
pub struct BounceGeometry {
    real: Geometry,
    object: Geometry,
    /// The object's bounding box (lo, hi); `None` without an object.
    object_box: Option<(Vec3, Vec3)>,
    /// The object's bounding sphere (centre, radius), from its box; `None` without an object.
    object_sphere: Option<(Vec3, f32)>,
    albedo: Vec<Vec3>,
}

impl BounceGeometry {
    pub fn new(scene: &Scene) -> Self {
        let real = match &scene.shadow_proxy {
            Some(proxy) => std::slice::from_ref(proxy.as_ref()),
            None => &scene.meshes,
        };
        Self::of_meshes(
            real,
            &scene.meshes,
            scene.materials.iter().map(|m| m.albedo).collect(),
        )
    }

    /// The real surface of `real`, the object of `with_object`'s virtual meshes, and each
    /// material's albedo.
    fn of_meshes(real: &[Mesh], with_object: &[Mesh], albedo: Vec<Vec3>) -> Self {
        let object: Vec<Mesh> = with_object
            .iter()
            .filter(|m| m.is_virtual)
            .cloned()
            .collect();
        let bounds = relight_core::scene::bounds(object.iter());
        Self {
            real: Geometry::of_meshes(real, false),
            object: Geometry::of_meshes(&object, true),
            object_box: bounds,
            object_sphere: bounds.map(|(lo, hi)| ((lo + hi) / 2.0, (hi - lo).length() / 2.0)),
            albedo,
        }
    }

    /// Where the object rays from `from` go ([`Aim`]); `None` without an object.
    fn aim(&self, from: Vec3) -> Option<Aim> {
        let (centre, radius) = self.object_sphere?;
        let to = centre - from;
        let distance = to.length();
        if !distance.is_finite() {
            return None;
        }
        if distance <= radius * 1.0001 {
            return Some(Aim::Hemisphere);
        }
        let sin_alpha = radius / distance;
        let cos_alpha = (1.0 - sin_alpha * sin_alpha).sqrt();
        Some(Aim::Cone {
            axis: to / distance,
            cos_alpha,
            solid_angle: std::f32::consts::TAU * (1.0 - cos_alpha),
        })
    }

    /// Where a ray from `origin` along `dir` lands, with the object or without it, carrying
    /// `flux` before the landing surface reflects it.
    fn land(&self, with_object: bool, origin: Vec3, dir: Vec3, flux: Vec3) -> Option<Landing> {
        let real = self.hit(&self.real, origin, dir, f32::INFINITY, flux);
        let object = with_object
            .then(|| self.hit(&self.object, origin, dir, f32::INFINITY, flux))
            .flatten();
        match (real, object) {
            (Some(r), Some(o)) => Some(if o.t < r.t { o } else { r }),
            (r, o) => r.or(o),
        }
    }

    /// The closest hit on `geometry` before `t_max`, carrying `flux` before it reflects it.
    fn hit(
        &self,
        geometry: &Geometry,
        origin: Vec3,
        dir: Vec3,
        t_max: f32,
        flux: Vec3,
    ) -> Option<Landing> {
        let hit = geometry.intersect(origin, dir, 0.0, t_max)?;
        let tri = geometry.triangles().get(hit.triangle)?;
        let albedo = tri
            .measured_albedo_at(hit.u, hit.v)
            .or_else(|| self.albedo.get(tri.material).copied())
            .unwrap_or(Vec3::ZERO);
        Some(Landing {
            t: hit.t,
            on_object: tri.is_virtual,
            position: origin + dir * hit.t,
            // The side the light arrives on.
            normal: tri.normal_against(dir),
            flux: flux * albedo,
        })
    }

    /// Whether nothing, real or virtual, lies between `origin` and `to` (a point on a surface,
    /// which does not count).
    fn clear(&self, origin: Vec3, to: Vec3) -> bool {
        let v = to - origin;
        let d = v.length();
        if d <= 0.0 || !d.is_finite() {
            return false;
        }
        let end = d * (1.0 - 1e-4);
        [&self.real, &self.object]
            .iter()
            .all(|g| g.occluder(origin, v / d, 0.0, end).is_none())
    }
}

/// The directions an object ray from a source is drawn from: every direction the object can
/// change a landing along.
#[derive(Debug, Clone, Copy)]
enum Aim {
    /// The cone of the object's bounding sphere (uniform in its solid angle), from outside it.
    Cone {
        axis: Vec3,
        cos_alpha: f32,
        solid_angle: f32,
    },
    /// From inside the sphere (beside the object, at its foot) the whole hemisphere, cosine
    /// distributed.
    Hemisphere,
}

impl Aim {
    /// At most the share of a Lambertian source's flux (normal `n`) sent into these directions:
    /// Ω · cos(max(θ_c − α, 0)) / π for the cone, θ_c its axis' angle from `n`; 1 for the
    /// hemisphere.
    fn flux_share_bound(self, n: Vec3) -> f32 {
        match self {
            Aim::Cone {
                axis,
                cos_alpha,
                solid_angle,
            } => {
                let theta_c = n.dot(axis).clamp(-1.0, 1.0).acos();
                let nearest = (theta_c - cos_alpha.acos()).max(0.0);
                if nearest < std::f32::consts::FRAC_PI_2 {
                    solid_angle * nearest.cos() / std::f32::consts::PI
                } else {
                    0.0
                }
            }
            Aim::Hemisphere => 1.0,
        }
    }

    /// A direction from `u` in [0, 1)², and the source's cos θ / π over its density there: the
    /// share of the source's flux the direction carries, per ray.
    fn direction(self, n: Vec3, u: [f32; 2]) -> (Vec3, f32) {
        match self {
            Aim::Cone {
                axis,
                cos_alpha,
                solid_angle,
            } => {
                let dir = cone_direction(axis, cos_alpha, u);
                (
                    dir,
                    n.dot(dir).max(0.0) * solid_angle / std::f32::consts::PI,
                )
            }
            Aim::Hemisphere => (cosine_direction(n, u), 1.0),
        }
    }

    /// The solid angle (sr) the directions span, which `k` rays share: the cone's; the
    /// hemisphere's projected one, π, as a cosine ray's footprint counts it.
    fn solid_angle(self) -> f32 {
        match self {
            Aim::Cone { solid_angle, .. } => solid_angle,
            Aim::Hemisphere => std::f32::consts::PI,
        }
    }
}

/// A second-bounce ray's landing: how far, on what, and the flux reflected there.
#[derive(Debug, Clone, Copy)]
struct Landing {
    t: f32,
    on_object: bool,
    position: Vec3,
    normal: Vec3,
    flux: Vec3,
}

impl Landing {
    /// The VPL, its 1/d² clamped within `clamp_m`.
    fn vpl(self, class: u32, clamp_m: f32) -> GpuVpl {
        GpuVpl::new(self.position, self.normal, self.flux, class, clamp_m)
    }
}

/// The second-bounce VPLs of `count` cosine rays and `object_rays` rays into the object's cone,
/// continuing `first` (the first-bounce VPLs; those without flux are skipped).
///
/// Cosine ray j continues first-bounce VPL ⌊(j + ½) n / count⌋ of the n with flux, each ray
/// standing for n / count of them, along a fixed low-discrepancy direction: the same first
/// bounce gives the same second, so a static scene does not flicker. A ray makes no VPL where
/// it leaves the scene, and two where a class-0 ray lands apart in the two scenes.
///
/// With `object_rays` > 0 and an object, every class-0 VPL splits its light: its cosine rays
/// keep only the landings the object does not change, and the object rays give those it does
/// ([`object_rays_vpls`], and [`object_face_vpls`] for the light landing on the object). At most
/// 2 · (`count` + `object.rays`) + [`ObjectBounce::face_cells`] VPLs.
pub fn second_bounce(
    geometry: &BounceGeometry,
    first: &[GpuVpl],
    count: usize,
    object: ObjectBounce,
) -> Vec<GpuVpl> {
    let object_rays = object.rays;
    let lit: Vec<&GpuVpl> = first
        .iter()
        .filter(|v| v.flux().max_element() > 0.0 && v.flux().is_finite())
        .collect();
    let mut out = Vec::with_capacity(2 * (count + object_rays));
    if lit.is_empty() || count == 0 {
        return out;
    }
    let split = |v: &GpuVpl| object_rays > 0 && v.class() == 0 && geometry.object_sphere.is_some();
    let share = lit.len() as f32 / count as f32;
    // A VPL stands for the patch its ray's share of the hemisphere (π/m of projected solid
    // angle, m = 1/share rays a first-bounce VPL) covers at the distance t it went: radius
    // t·√(share). Nearer than a part of that its 1/d² is a point's, not the patch's, and
    // spikes (on desk_box one such VPL put 0.82 into a pixel whose Δ is 0.07).
    let footprint = FOOTPRINT * share.sqrt();
    for j in 0..count {
        let source = lit[((j as f32 + 0.5) * share) as usize % lit.len()];
        let (p, n) = (source.position(), source.normal());
        if n == Vec3::ZERO || !p.is_finite() {
            continue;
        }
        let dir = cosine_direction(n, r2(j as u32));
        let origin = ray_origin(p, n);
        let flux = source.flux() * share;
        let rho = || geometry.land(true, origin, dir, flux);
        let mu = || geometry.land(false, origin, dir, flux);
        let vpl = |landed: Option<Landing>, class| landed.map(|l| l.vpl(class, footprint * l.t));
        match source.class() {
            1 => out.extend(vpl(rho(), 1)),
            2 => out.extend(vpl(mu(), 2)),
            _ => match (rho(), mu()) {
                (a, Some(b)) if unchanged(a, b) => out.push(b.vpl(0, footprint * b.t)),
                // The object rays give these.
                _ if split(source) => {}
                (a, b) => out.extend(vpl(a, 1).into_iter().chain(vpl(b, 2))),
            },
        }
    }
    let sources: Vec<&GpuVpl> = lit.into_iter().filter(|v| split(v)).collect();
    let faces = object.cells > 0;
    out.extend(object_rays_vpls(geometry, &sources, object_rays, !faces));
    if faces {
        out.extend(object_face_vpls(
            geometry,
            &sources,
            object.cells,
            object.clamp_m,
        ));
    }
    out
}

/// How the second bounce takes the light the object changes ([`second_bounce`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ObjectBounce {
    /// Rays aimed at the object ([`object_rays_vpls`]); 0: the cosine rays carry that light.
    pub rays: usize,
    /// With rays, the light landing on the object from cells × cells points on each face of its
    /// box ([`object_face_vpls`]) instead of where the rays land on it; 0: the rays' landings.
    pub cells: u32,
    /// The smallest radius (m) within which the gather clamps a VPL's 1/d²
    /// (`clamp_distance`), which the cells' irradiance takes as well.
    pub clamp_m: f32,
}

impl ObjectBounce {
    /// The most VPLs [`object_face_vpls`] makes: one per cell of the box's six faces.
    pub fn face_cells(&self) -> usize {
        if self.rays == 0 {
            return 0;
        }
        6 * self.cells as usize * self.cells as usize
    }
}

/// The part of each of `sources`' (class-0 VPLs) light that the object changes, by `count` rays
/// aimed where it can ([`Aim`]).
///
/// Sources are chosen in proportion to a bound of the flux they send there
/// ([`Aim::flux_share_bound`]), on a fixed stratification like the cosine rays', so the rays go
/// where the object changes the most light. A ray that lands on the same real surface with the
/// object and without it makes nothing (the cosine rays carry that light); one the object
/// changes makes its class-1 and class-2 VPLs, each carrying Φ · (cos θ / π) / (density ·
/// count · P(source)). Its footprint is its share of the directions' solid angle A among the
/// k rays its source expects ([`Aim::solid_angle`]): radius t·√(A / (π k)), as a cosine ray's.
/// With `on_object` false, a ray's landing on the object makes nothing ([`object_face_vpls`]
/// gives that light), only the landing without it that the object takes away.
fn object_rays_vpls(
    geometry: &BounceGeometry,
    sources: &[&GpuVpl],
    count: usize,
    on_object: bool,
) -> Vec<GpuVpl> {
    let mut out = Vec::new();
    let aims: Vec<Option<Aim>> = sources.iter().map(|v| geometry.aim(v.position())).collect();
    let weights: Vec<f32> = sources
        .iter()
        .zip(&aims)
        .map(|(v, aim)| {
            aim.map_or(0.0, |aim| {
                v.flux().max_element() * aim.flux_share_bound(v.normal())
            })
        })
        .collect();
    let total: f32 = weights.iter().sum();
    if count == 0 || total <= 0.0 || !total.is_finite() {
        return out;
    }
    let (mut cumulative, mut chosen) = (0.0, 0);
    for j in 0..count {
        let target = (j as f32 + 0.5) / count as f32 * total;
        while chosen + 1 < weights.len() && cumulative + weights[chosen] < target {
            cumulative += weights[chosen];
            chosen += 1;
        }
        let (source, Some(aim)) = (sources[chosen], aims[chosen]) else {
            continue;
        };
        let (p, n) = (source.position(), source.normal());
        let (dir, share) = aim.direction(n, r2(j as u32));
        let expected_rays = weights[chosen] / total * count as f32;
        if share <= 0.0 || n == Vec3::ZERO || !p.is_finite() {
            continue;
        }
        let origin = ray_origin(p, n);
        let flux = source.flux() * (share / expected_rays);
        let footprint =
            FOOTPRINT * (aim.solid_angle() / (std::f32::consts::PI * expected_rays)).sqrt();
        let rho = geometry.land(true, origin, dir, flux);
        let mu = geometry.land(false, origin, dir, flux);
        match (rho, mu) {
            (a, Some(b)) if unchanged(a, b) => {}
            (a, b) => out.extend(
                [(a.filter(|_| on_object), 1), (b, 2)]
                    .into_iter()
                    .filter_map(|(l, class)| l.map(|l| l.vpl(class, footprint * l.t))),
            ),
        }
    }
    out
}

/// The light the `sources` (class-0 VPLs, which light the real scene with the object and
/// without it) put directly on the object, as class-1 VPLs: one at each of `cells` × `cells`
/// points over each face of the object's bounding box, where a ray from outside the face,
/// straight in, meets the object, of flux ρ · E · A. E is the sources' irradiance there, each a
/// point of cosine intensity Φ/π cos θ whose 1/d² is clamped as the gather clamps it (within
/// its own footprint and `clamp_m`), seen through the scene with the object; A the surface the
/// point stands for (the cell's area over the cosine of its normal to the face's axis). A point
/// counts on the face whose axis its normal is nearest, as the gather's squares of the box's
/// faces do (`box_square_quad` in `shaders/common.wgsl`), so a box's faces are each taken once.
///
/// Why: the object rays' landings on the object are a few dozen points where chance puts
/// them, and a real surface beside the object sees its nearest face over up to half its
/// hemisphere: a landing near desk_box's foot, standing for a large part of the face's light,
/// put the floor there at three times the reference's Δ. The irradiance on a fixed grid has no
/// such chance (the same sources give the same VPLs), at `cells`² · 6 · sources visibility
/// rays, on the CPU in parallel. What it cannot do: a surface of the object hidden from all
/// six sides (a cup's inside) takes no second bounce.
fn object_face_vpls(
    geometry: &BounceGeometry,
    sources: &[&GpuVpl],
    cells: u32,
    clamp_m: f32,
) -> Vec<GpuVpl> {
    use rayon::prelude::*;
    let Some((lo, hi)) = geometry.object_box else {
        return Vec::new();
    };
    if sources.is_empty() {
        return Vec::new();
    }
    let size = hi - lo;
    let margin = 1e-3 * size.max_element().max(1e-3);
    let n = cells as usize;
    let points: Vec<(usize, f32, usize, usize)> = (0..3)
        .flat_map(|axis| [1.0f32, -1.0].map(|sign| (axis, sign)))
        .flat_map(|(axis, sign)| (0..n * n).map(move |c| (axis, sign, c % n, c / n)))
        .collect();
    points
        .par_iter()
        .filter_map(|&(axis, sign, i, j)| {
            let (t, b) = ((axis + 1) % 3, (axis + 2) % 3);
            let cell_area = size[t] * size[b] / (n * n) as f32;
            if cell_area <= 0.0 {
                return None;
            }
            let mut origin = lo;
            origin[t] += (i as f32 + 0.5) / n as f32 * size[t];
            origin[b] += (j as f32 + 0.5) / n as f32 * size[b];
            origin[axis] = if sign > 0.0 { hi[axis] } else { lo[axis] } + sign * margin;
            let dir = Vec3::AXES[axis] * -sign;
            let on = geometry
                .hit(
                    &geometry.object,
                    origin,
                    dir,
                    size[axis] + 2.0 * margin,
                    Vec3::ONE,
                )
                .filter(|l| nearest_axis(l.normal) == axis && l.normal[axis] * sign > 0.0)?;
            let irradiance: Vec3 = sources
                .iter()
                .map(|s| {
                    let (p, ns) = (s.position(), s.normal());
                    let v = on.position - p;
                    let d2 = v.length_squared();
                    let w = v / d2.sqrt();
                    let (cos_source, cos_on) = (ns.dot(w), -on.normal.dot(w));
                    // (NaN at d = 0 fails the test too.)
                    let lit = cos_source > 0.0
                        && cos_on > 0.0
                        && geometry.clear(ray_origin(p, ns), on.position);
                    if !lit {
                        return Vec3::ZERO;
                    }
                    let cosines = cos_source * cos_on;
                    let r = clamp_m.max(s.normal[3]);
                    s.flux() * (cosines / (std::f32::consts::PI * d2.max(r * r)))
                })
                .sum();
            let area = cell_area / on.normal[axis].abs();
            // The disc of the cell's area on the face: the gather's square of the face
            // (half edge √π/2 times this) is then the cell.
            let footprint = (cell_area / std::f32::consts::PI).sqrt();
            (irradiance.max_element() > 0.0).then(|| {
                GpuVpl::new(
                    on.position,
                    on.normal,
                    on.flux * irradiance * area,
                    1,
                    footprint,
                )
            })
        })
        .collect()
}

/// The axis a normal is nearest, ties as `box_square_quad` in `shaders/common.wgsl` breaks them.
fn nearest_axis(n: Vec3) -> usize {
    let a = n.abs();
    if a.y >= a.x && a.y >= a.z {
        1
    } else if a.z >= a.x && a.z >= a.y {
        2
    } else {
        0
    }
}

/// Where a ray from a VPL at `p` (normal `n`) starts: just off its surface.
fn ray_origin(p: Vec3, n: Vec3) -> Vec3 {
    p + n * (1e-4 * (1.0 + p.abs().max_element()))
}

/// Whether a ray landed on the same real surface with the object (`with`) and without it
/// (`without`): the object plays no part in its path.
fn unchanged(with: Option<Landing>, without: Landing) -> bool {
    with.is_some_and(|a| !a.on_object && (a.t - without.t).abs() <= 1e-5 * without.t)
}

/// A direction uniform in the cone of half angle acos(`cos_alpha`) about `axis`, from `u` in
/// [0, 1)².
fn cone_direction(axis: Vec3, cos_alpha: f32, [u, v]: [f32; 2]) -> Vec3 {
    let (t, b) = axis.any_orthonormal_pair();
    let cos = 1.0 - u * (1.0 - cos_alpha);
    let sin = (1.0 - cos * cos).max(0.0).sqrt();
    let phi = std::f32::consts::TAU * v;
    (t * (sin * phi.cos()) + b * (sin * phi.sin()) + axis * cos).normalize()
}

/// The share of a VPL's footprint radius within which its 1/d² is clamped.
const FOOTPRINT: f32 = 1.0;

/// The j-th point of the R2 sequence (Roberts 2018) in [0, 1)².
fn r2(j: u32) -> [f32; 2] {
    const G: f64 = 1.324_717_957_244_746;
    let j = f64::from(j) + 1.0;
    [
        (0.5 + j / G).fract() as f32,
        (0.5 + j / (G * G)).fract() as f32,
    ]
}

/// A direction about `n` with density cos θ / π, from `u` in [0, 1)².
fn cosine_direction(n: Vec3, [u, v]: [f32; 2]) -> Vec3 {
    let (t, b) = n.any_orthonormal_pair();
    let r = u.sqrt();
    let phi = std::f32::consts::TAU * v;
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - u).max(0.0).sqrt()).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `count` object rays, their landings on the object kept.
    fn rays(count: usize) -> ObjectBounce {
        ObjectBounce {
            rays: count,
            ..ObjectBounce::default()
        }
    }

    /// A square of side 2 m at height `z`, facing `up` or down, of material `material`.
    fn square(z: f32, up: bool, material: usize, is_virtual: bool) -> Mesh {
        let p =
            [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(x, y)| Vec3::new(x, y, z));
        let n = if up { Vec3::Z } else { Vec3::NEG_Z };
        let triangles = if up {
            vec![[0, 1, 2], [0, 2, 3]]
        } else {
            vec![[0, 2, 1], [0, 3, 2]]
        };
        Mesh {
            name: format!("square at {z}"),
            positions_in_world: p.to_vec(),
            normals_in_world: vec![n; 4],
            triangles,
            material,
            is_virtual,
            vertex_albedo: Vec::new(),
        }
    }

    /// A floor (albedo 0.5) under a ceiling (albedo 0.8) 1 m up, and optionally a virtual
    /// plate (albedo 0.2) between them at 0.5 m.
    fn room(plate: bool) -> BounceGeometry {
        let mut meshes = vec![square(0.0, true, 0, false), square(1.0, false, 1, false)];
        if plate {
            meshes.push(square(0.5, false, 2, true));
        }
        BounceGeometry::of_meshes(&meshes, &meshes, [0.5, 0.8, 0.2].map(Vec3::splat).to_vec())
    }

    /// The room of [`room`] with a virtual plate of half edge 0.1 m (albedo 0.2) at `height`.
    fn plate_room(height: f32) -> BounceGeometry {
        let mut plate = square(height, false, 2, true);
        for p in &mut plate.positions_in_world {
            *p = Vec3::new(p.x * 0.1, p.y * 0.1, p.z);
        }
        let meshes = [
            square(0.0, true, 0, false),
            square(1.0, false, 1, false),
            plate,
        ];
        BounceGeometry::of_meshes(&meshes, &meshes, [0.5, 0.8, 0.2].map(Vec3::splat).to_vec())
    }

    fn floor_vpl(class: u32) -> GpuVpl {
        GpuVpl::new(
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::Z,
            Vec3::splat(2.0),
            class,
            0.0,
        )
    }

    #[test]
    fn without_the_object_every_second_bounce_lights_both_solutions() {
        let geometry = room(false);
        let landed = second_bounce(&geometry, &[floor_vpl(0)], 64, rays(0));
        // Half the cosine-distributed rays (sin² θ < 1/2) meet the 2 m ceiling 1 m up.
        assert!(
            (24..=40).contains(&landed.len()),
            "{} of 64 landed",
            landed.len()
        );
        for v in &landed {
            assert_eq!(v.class(), 0);
            // On the ceiling, facing down, with Φ/m · 0.8 (m = 64 rays from the one VPL).
            assert!((v.position[2] - 1.0).abs() < 1e-4, "{v:?}");
            assert_eq!(v.normal[2], -1.0);
            assert!((v.flux[0] - 2.0 / 64.0 * 0.8).abs() < 1e-6, "{v:?}");
        }
    }

    #[test]
    fn the_object_takes_the_real_second_bounce_and_gives_its_own() {
        let geometry = room(true);
        let vpls = second_bounce(&geometry, &[floor_vpl(0)], 64, rays(0));
        let of = |class| vpls.iter().filter(move |v| v.class() == class);
        // The plate, half-way up, stops every ray the ceiling would (and more): each lands on
        // the plate (class 1, albedo 0.2) in the scene with it, and on the ceiling (class 2,
        // albedo 0.8) without it where it reaches the ceiling.
        assert_eq!(of(0).count(), 0, "{vpls:?}");
        assert!(
            of(1).count() > of(2).count() && of(2).count() > 20,
            "{vpls:?}"
        );
        for v in of(1) {
            assert!((v.position[2] - 0.5).abs() < 1e-4);
            assert!((v.flux[0] - 2.0 / 64.0 * 0.2).abs() < 1e-6);
        }
        for v in of(2) {
            assert!((v.position[2] - 1.0).abs() < 1e-4);
            assert!((v.flux[0] - 2.0 / 64.0 * 0.8).abs() < 1e-6);
        }
    }

    #[test]
    fn the_object_s_own_vpls_bounce_in_its_scene_and_blocked_ones_in_the_real_one() {
        let geometry = room(true);
        let on_object = GpuVpl::new(Vec3::new(0.0, 0.0, 0.5), Vec3::NEG_Z, Vec3::ONE, 1, 0.0);
        let vpls = second_bounce(&geometry, &[on_object], 16, rays(0));
        assert!(!vpls.is_empty() && vpls.iter().all(|v| v.class() == 1));
        let landed = second_bounce(&geometry, &[floor_vpl(2)], 16, rays(0));
        assert!(!landed.is_empty());
        assert!(
            landed
                .iter()
                .all(|v| v.class() == 2 && (v.position[2] - 1.0).abs() < 1e-4)
        );
    }

    /// The form factor from a point to a square of half edge `a` centred `h` above it,
    /// parallel: four rectangles with a corner over the point (Howell's catalogue, C-11).
    fn square_form_factor(a: f64, h: f64) -> f64 {
        let x = a / h;
        let s = (1.0 + x * x).sqrt();
        4.0 * (2.0 * x / s * (x / s).atan()) / (2.0 * std::f64::consts::PI)
    }

    /// A floor VPL under the middle of a virtual plate of half edge 0.1 m at `height`, below a
    /// ceiling of half edge 1 m, 1 m up: the light landing on the plate is the VPL's flux times
    /// the form factor to it times the plate's albedo (class 1), and the light the plate takes
    /// from the ceiling is the flux times the form factor of the directions through the plate
    /// that reach the ceiling, times the ceiling's albedo (class 2). From 0.5 m the object rays are
    /// aimed into the plate's bounding cone, from 0.05 m (inside its sphere) over the
    /// hemisphere. The R2 directions' error at 256 rays is about 1 %; 64 cosine rays alone
    /// would meet a plate of form factor 0.07 about 4 times.
    #[test]
    fn object_rays_carry_the_light_the_object_changes() {
        for height in [0.5f32, 0.05] {
            let geometry = plate_room(height);
            let vpls = second_bounce(&geometry, &[floor_vpl(0)], 64, rays(256));
            let flux = |class| -> f64 {
                vpls.iter()
                    .filter(|v| v.class() == class)
                    .map(|v| f64::from(v.flux[0]))
                    .sum()
            };
            let f = square_form_factor(0.1, f64::from(height));
            println!(
                "height {height}: F {f:.4}, class 1 {:.4}, class 2 {:.4}",
                flux(1),
                flux(2)
            );
            // Without the plate, the rays through it land on the ceiling where the ceiling
            // spans them: within the narrower of the two squares of directions.
            let through_to_ceiling = square_form_factor((0.1 / f64::from(height)).min(1.0), 1.0);
            for (class, expected) in [(1, 2.0 * f * 0.2), (2, 2.0 * through_to_ceiling * 0.8)] {
                assert!(
                    (flux(class) / expected - 1.0).abs() < 0.03,
                    "height {height}, class {class}: {} against {expected}",
                    flux(class)
                );
            }
            // Spread over many rays (the plate fills 2/π of its bounding cone), not left to
            // the few cosine rays that would meet it.
            let on_plate = vpls.iter().filter(|v| v.class() == 1).count();
            assert!(
                on_plate >= 128,
                "height {height}: {on_plate} rays on the plate"
            );
            // The cosine rays keep the rest: none of theirs lands on the plate.
            assert!(
                vpls.iter()
                    .filter(|v| v.class() == 0)
                    .all(|v| (v.position[2] - 1.0).abs() < 1e-4)
            );
        }
    }

    /// With `cells`, the light landing on the object comes from the grid of its faces, not from
    /// where the object rays land: for the floor VPL under the plate of
    /// `object_rays_carry_the_light_the_object_changes`, the cells' flux is the VPL's flux times
    /// the form factor to the plate times the plate's albedo, on its face towards the floor
    /// alone. The cells sample the irradiance at their centres (the midpoint rule), which read
    /// 0.3 % over at 0.5 m with 4 × 4 and 0.2 % over at 0.05 m with 8 × 8 (2 % allowed). The
    /// object rays still give the light the plate takes from the ceiling.
    #[test]
    fn the_object_s_faces_take_the_light_that_lands_on_it() {
        for (height, cells) in [(0.5f32, 4), (0.05, 8)] {
            let geometry = plate_room(height);
            let object = ObjectBounce {
                rays: 256,
                cells,
                clamp_m: 0.0,
            };
            let vpls = second_bounce(&geometry, &[floor_vpl(0)], 64, object);
            let on_plate: Vec<&GpuVpl> = vpls.iter().filter(|v| v.class() == 1).collect();
            assert_eq!(on_plate.len(), (cells * cells) as usize, "height {height}");
            for v in &on_plate {
                assert!((v.position[2] - height).abs() < 1e-4, "{v:?}");
                assert_eq!(v.normal[2], -1.0, "{v:?}");
            }
            let flux: f64 = on_plate.iter().map(|v| f64::from(v.flux[0])).sum();
            let expected = 2.0 * square_form_factor(0.1, f64::from(height)) * 0.2;
            println!("height {height}: {flux:.5} against {expected:.5}");
            assert!(
                (flux / expected - 1.0).abs() < 0.02,
                "height {height}: {flux} against {expected}"
            );
            assert!(
                vpls.iter().filter(|v| v.class() == 2).count() >= 128,
                "height {height}: the light the plate takes from the ceiling"
            );
            assert_eq!(object.face_cells(), 6 * (cells * cells) as usize);
        }
    }

    /// An object that is not its box: a cube of edge 1 m turned 45° about x, 100 m above a
    /// floor VPL. Its four turned faces are each taken once, from the box's faces their
    /// normals are nearest (a tie of y and z goes to y, as `box_square_quad` breaks it), each
    /// point standing for its cell over the cosine to that axis; the light landing on it is
    /// the VPL's intensity Φ/π times the cube's area seen from below (1 × √2) over 100²,
    /// within the 1/d² spread over its lit faces (under 1 %; it reads 0.35 % over).
    #[test]
    fn a_turned_object_s_faces_are_each_taken_once() {
        let (c, s) = (
            std::f32::consts::FRAC_PI_4.cos(),
            std::f32::consts::FRAC_PI_4.sin(),
        );
        let corners: Vec<Vec3> = (0..8)
            .map(|i| {
                let p = glam::UVec3::new(i & 1, (i >> 1) & 1, (i >> 2) & 1).as_vec3() - 0.5;
                Vec3::new(p.x, c * p.y - s * p.z, s * p.y + c * p.z + 100.0)
            })
            .collect();
        let triangles = [
            [0, 1, 3, 2],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 3, 7, 5],
        ]
        .iter()
        .flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]])
        .collect();
        let cube = Mesh {
            name: "turned cube".into(),
            positions_in_world: corners,
            normals_in_world: vec![Vec3::Z; 8],
            triangles,
            material: 2,
            is_virtual: true,
            vertex_albedo: Vec::new(),
        };
        let meshes = [square(0.0, true, 0, false), cube];
        let albedo = [0.5, 0.8, 0.2].map(Vec3::splat).to_vec();
        let geometry = BounceGeometry::of_meshes(&meshes, &meshes, albedo);
        let object = ObjectBounce {
            rays: 64,
            cells: 4,
            clamp_m: 0.0,
        };
        let on_cube: Vec<GpuVpl> = second_bounce(&geometry, &[floor_vpl(0)], 16, object)
            .into_iter()
            .filter(|v| v.class() == 1)
            .collect();
        // Half of each of the ±y faces' 16 cells meets a lower (lit) face.
        assert_eq!(on_cube.len(), 16, "{on_cube:?}");
        for v in &on_cube {
            assert!(
                (v.normal[1].abs() - c).abs() < 1e-4 && v.normal[2] < 0.0,
                "{v:?}"
            );
        }
        let flux: f64 = on_cube.iter().map(|v| f64::from(v.flux[0])).sum();
        let expected = 2.0 / std::f64::consts::PI * 2f64.sqrt() / 1e4 * 0.2;
        println!("turned cube: {flux:.6e} against {expected:.6e}");
        assert!(
            (flux / expected - 1.0).abs() < 0.01,
            "{flux} against {expected}"
        );
    }

    #[test]
    fn the_same_first_bounce_gives_the_same_second() {
        let geometry = room(true);
        let first = [floor_vpl(0), floor_vpl(1), floor_vpl(2)];
        assert_eq!(
            second_bounce(&geometry, &first, 32, rays(8)),
            second_bounce(&geometry, &first, 32, rays(8))
        );
        assert!(second_bounce(&geometry, &[], 8, rays(8)).is_empty());
    }
}
