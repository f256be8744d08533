//! Light sources from an environment map: the median cut of Debevec ("A median cut algorithm for
//! light probe sampling", SIGGRAPH 2005 poster) and the variance-minimising median cut of
//! Viriyothai & Debevec ("Variance minimization light probe sampling", SIGGRAPH 2009 poster).
//!
//! Both split the equirectangular map into rectangles of texels, recursively, and put one
//! directional light per region at its energy centroid with the region's total energy:
//!
//! - energy of a texel is its luminance (Rec. 709) times its exact solid angle (the cos-latitude
//!   weighting of the papers, exact instead of sampled at the centre);
//! - median cut splits a region across its longest dimension — width scaled by the cosine of
//!   the region's central latitude, against height — where the energy is halved;
//! - variance minimisation tries every cut along both axes and keeps the one minimising the larger
//!   of the two halves' energy-weighted variance `Σ e_p d_p²` (`d_p`: distance of texel `p` to the
//!   region's centroid). Here `d_p` is the chord between unit directions rather than a distance
//!   in the lat-long image, so that the variance means the same at every latitude;
//!   `Σ e |d − c|² = Σ e − |Σ e d|² / Σ e` for unit `d`, so four summed-area tables (e and e·d)
//!   give any region's energy, centroid and variance in O(1).
//!
//! Light count: the papers split every region each round, giving `2^n` lights. For any `N`,
//! rounds split every splittable region while the count stays within `N`; the last, partial
//! round splits the `N − count` regions with the most energy (median cut) or the largest variance
//! (variance minimisation). For `N = 2^n` this is the papers' algorithm exactly (as long as every
//! region can be split). A region of one texel, or without energy, is not split, so fewer than
//! `N` lights can come out; `N = 0` gives none.
//!
//! Lights: direction at the region's energy centroid, taken as the normalised energy-weighted mean
//! of its texel directions (the papers take it in the lat-long image: the same for small regions,
//! and still on the region's energy for wide ones near a pole), RGB irradiance `Σ L ΔΩ` over the
//! region — so the lights sum exactly to the map's energy ([`crate::envmap::map_energy`]).
//! Regions without energy give no light.

use glam::{DVec3, Vec3};
use relight_core::light::Light;
use relight_core::scene::EnvironmentMap;

use crate::envmap::{EnvMapError, check_map, sanitized, texel_direction, texel_solid_angle};

/// Rec. 709 luminance weights (those of `relight_core::sh`).
const LUMINANCE: DVec3 = DVec3::new(0.2126, 0.7152, 0.0722);

/// Which splitting rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CutMethod {
    /// Debevec 2005: halve the energy across the longest dimension.
    MedianCut,
    /// Viriyothai & Debevec 2009: minimise the larger half's energy-weighted variance.
    #[default]
    VarianceMinimizing,
}

/// What [`extract_lights`] does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MedianCutSettings {
    pub method: CutMethod,
    /// Number of regions (lights) wanted; any positive number (module docs).
    pub light_count: usize,
}

impl Default for MedianCutSettings {
    fn default() -> Self {
        Self {
            method: CutMethod::default(),
            light_count: 16,
        }
    }
}

/// A rectangle of texels `[x0, x1) × [y0, y1)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TexelRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl TexelRect {
    pub fn width(&self) -> u32 {
        self.x1 - self.x0
    }

    pub fn height(&self) -> u32 {
        self.y1 - self.y0
    }
}

/// One region's light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegionLight {
    /// Unit world direction from the scene towards the region's energy centroid.
    pub direction_to_light: Vec3,
    /// `Σ L ΔΩ` over the region, W/m² per channel: the irradiance on a surface facing it.
    pub irradiance: Vec3,
    pub region: TexelRect,
}

impl RegionLight {
    /// The region as a distant light.
    pub fn to_light(&self) -> Light {
        Light::Directional {
            direction_in_world: -self.direction_to_light,
            irradiance: self.irradiance,
        }
    }
}

/// Splits `map` into regions and returns one light per region with energy, brightest
/// (by luminance) first. An all-dark map, or a count of 0, gives no lights; see the module docs
/// for the rules.
pub fn extract_lights(
    map: &EnvironmentMap,
    settings: &MedianCutSettings,
) -> Result<Vec<RegionLight>, EnvMapError> {
    check_map(map)?;
    if settings.light_count == 0 {
        return Ok(Vec::new());
    }
    let table = EnergyTable::new(map);
    let whole = TexelRect {
        x0: 0,
        y0: 0,
        x1: map.width,
        y1: map.height,
    };
    let mut regions = vec![whole];
    while regions.len() < settings.light_count {
        let mut candidates: Vec<(usize, f64)> = regions
            .iter()
            .enumerate()
            .filter(|(_, r)| table.energy(r) > 0.0 && r.width() * r.height() > 1)
            .map(|(i, r)| {
                let priority = match settings.method {
                    CutMethod::MedianCut => table.energy(r),
                    CutMethod::VarianceMinimizing => table.variance(r),
                };
                (i, priority)
            })
            .collect();
        if candidates.is_empty() {
            break;
        }
        let room = settings.light_count - regions.len();
        if candidates.len() > room {
            candidates.sort_by(|a, b| b.1.total_cmp(&a.1));
            candidates.truncate(room);
        }
        let mut split = Vec::with_capacity(regions.len() + candidates.len());
        let chosen: Vec<usize> = candidates.iter().map(|(i, _)| *i).collect();
        for (i, region) in regions.iter().enumerate() {
            if chosen.contains(&i) {
                let (a, b) = match settings.method {
                    CutMethod::MedianCut => table.median_cut(region),
                    CutMethod::VarianceMinimizing => table.variance_cut(region),
                };
                split.extend([a, b]);
            } else {
                split.push(*region);
            }
        }
        regions = split;
    }
    let mut lights: Vec<RegionLight> = regions
        .iter()
        .filter(|r| table.energy(r) > 0.0)
        .map(|r| table.light(r))
        .collect();
    lights.sort_by(|a, b| {
        let lum = |l: &RegionLight| l.irradiance.as_dvec3().dot(LUMINANCE);
        lum(b).total_cmp(&lum(a))
    });
    Ok(lights)
}

/// Channels of the summed-area table.
const ENERGY: usize = 0;
const MOMENT: usize = 1; // 1..4: energy × direction (x, y, z)
const RGB: usize = 4; // 4..7: L ΔΩ per channel
const CHANNELS: usize = 7;

/// Summed-area tables (f64, so a 1e6:1 sun does not swallow the sky) of a map's texel energy,
/// energy-weighted directions and RGB energy.
struct EnergyTable {
    width: u32,
    height: u32,
    /// `(width + 1) × (height + 1)` prefix sums, row-major.
    sums: Vec<[f64; CHANNELS]>,
}

impl EnergyTable {
    fn new(map: &EnvironmentMap) -> Self {
        let (w, h) = (map.width as usize, map.height as usize);
        let mut sums = vec![[0.0f64; CHANNELS]; (w + 1) * (h + 1)];
        for y in 0..h {
            let solid_angle = texel_solid_angle(map.width, map.height, y as u32);
            let mut row = [0.0f64; CHANNELS];
            for x in 0..w {
                let rgb = sanitized(map.radiance[y * w + x]).as_dvec3() * solid_angle;
                let energy = rgb.dot(LUMINANCE);
                let dir = texel_direction(map.width, map.height, x as u32, y as u32).as_dvec3();
                let texel = [
                    energy,
                    energy * dir.x,
                    energy * dir.y,
                    energy * dir.z,
                    rgb.x,
                    rgb.y,
                    rgb.z,
                ];
                for (r, t) in row.iter_mut().zip(texel) {
                    *r += t;
                }
                let above = sums[y * (w + 1) + x + 1];
                let cell = &mut sums[(y + 1) * (w + 1) + x + 1];
                for c in 0..CHANNELS {
                    cell[c] = above[c] + row[c];
                }
            }
        }
        Self {
            width: map.width,
            height: map.height,
            sums,
        }
    }

    fn sum(&self, r: &TexelRect, channel: usize) -> f64 {
        let stride = self.width as usize + 1;
        let at = |x: u32, y: u32| self.sums[y as usize * stride + x as usize][channel];
        at(r.x1, r.y1) - at(r.x0, r.y1) - at(r.x1, r.y0) + at(r.x0, r.y0)
    }

    fn energy(&self, r: &TexelRect) -> f64 {
        self.sum(r, ENERGY).max(0.0)
    }

    fn moment(&self, r: &TexelRect) -> DVec3 {
        DVec3::new(
            self.sum(r, MOMENT),
            self.sum(r, MOMENT + 1),
            self.sum(r, MOMENT + 2),
        )
    }

    /// `Σ e |d − c|²` with `c` the energy-weighted mean direction.
    fn variance(&self, r: &TexelRect) -> f64 {
        let energy = self.energy(r);
        if energy <= 0.0 {
            return 0.0;
        }
        (energy - self.moment(r).length_squared() / energy).max(0.0)
    }

    fn light(&self, r: &TexelRect) -> RegionLight {
        let moment = self.moment(r);
        // The centroid of a region symmetric about the origin (a whole uniform map) is
        // undefined: fall back to the region's central direction.
        let direction = if moment.length() > 1e-9 * self.energy(r) {
            moment.normalize()
        } else {
            let (x, y) = ((r.x0 + r.x1) / 2, (r.y0 + r.y1) / 2);
            texel_direction(
                self.width,
                self.height,
                x.min(self.width - 1),
                y.min(self.height - 1),
            )
            .as_dvec3()
        };
        let rgb = DVec3::new(
            self.sum(r, RGB).max(0.0),
            self.sum(r, RGB + 1).max(0.0),
            self.sum(r, RGB + 2).max(0.0),
        );
        RegionLight {
            direction_to_light: direction.as_vec3(),
            irradiance: rgb.as_vec3(),
            region: *r,
        }
    }

    /// The two halves of `r` cut at `at` along x (`vertical`) or y.
    fn halves(r: &TexelRect, vertical: bool, at: u32) -> (TexelRect, TexelRect) {
        if vertical {
            (TexelRect { x1: at, ..*r }, TexelRect { x0: at, ..*r })
        } else {
            (TexelRect { y1: at, ..*r }, TexelRect { y0: at, ..*r })
        }
    }

    /// Cut positions that leave both halves non-empty.
    fn cuts(r: &TexelRect, vertical: bool) -> std::ops::Range<u32> {
        if vertical {
            r.x0 + 1..r.x1
        } else {
            r.y0 + 1..r.y1
        }
    }

    /// Debevec 2005: across the longest dimension (angular width `Δφ · cos(latitude)` at the
    /// region's central latitude, against angular height), where the energy is closest to half.
    fn median_cut(&self, r: &TexelRect) -> (TexelRect, TexelRect) {
        let theta_centre =
            std::f64::consts::PI * f64::from(r.y0 + r.y1) / 2.0 / f64::from(self.height);
        let angular_width = std::f64::consts::TAU * f64::from(r.width()) / f64::from(self.width)
            * theta_centre.sin();
        let angular_height = std::f64::consts::PI * f64::from(r.height()) / f64::from(self.height);
        let vertical = if r.width() == 1 {
            false
        } else if r.height() == 1 {
            true
        } else {
            angular_width >= angular_height
        };
        let half = self.energy(r) / 2.0;
        let at = Self::cuts(r, vertical)
            .min_by(|&a, &b| {
                let off = |at| (self.energy(&Self::halves(r, vertical, at).0) - half).abs();
                off(a).total_cmp(&off(b))
            })
            .unwrap_or(if vertical { r.x0 + 1 } else { r.y0 + 1 });
        Self::halves(r, vertical, at)
    }

    /// Viriyothai & Debevec 2009: the cut, along either axis, minimising the larger variance of
    /// the two halves (ties: the more balanced energy split).
    fn variance_cut(&self, r: &TexelRect) -> (TexelRect, TexelRect) {
        let half = self.energy(r) / 2.0;
        let mut best: Option<((f64, f64), TexelRect, TexelRect)> = None;
        for vertical in [true, false] {
            for at in Self::cuts(r, vertical) {
                let (a, b) = Self::halves(r, vertical, at);
                let key = (
                    self.variance(&a).max(self.variance(&b)),
                    (self.energy(&a) - half).abs(),
                );
                if best.as_ref().is_none_or(|(k, ..)| key < *k) {
                    best = Some((key, a, b));
                }
            }
        }
        match best {
            Some((_, a, b)) => (a, b),
            None => Self::halves(
                r,
                r.width() > 1,
                if r.width() > 1 { r.x0 + 1 } else { r.y0 + 1 },
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(width: u32, height: u32, f: impl Fn(u32, u32) -> f32) -> EnvironmentMap {
        EnvironmentMap {
            width,
            height,
            radiance: (0..width * height)
                .map(|i| Vec3::splat(f(i % width, i / width)))
                .collect(),
        }
    }

    #[test]
    fn table_sums_match_direct_sums() {
        let m = map(16, 8, |x, y| (x * 3 + y) as f32 * 0.1);
        let table = EnergyTable::new(&m);
        let r = TexelRect {
            x0: 3,
            y0: 2,
            x1: 9,
            y1: 7,
        };
        let mut direct = 0.0;
        for y in r.y0..r.y1 {
            for x in r.x0..r.x1 {
                direct +=
                    f64::from(m.radiance[(y * 16 + x) as usize].x) * texel_solid_angle(16, 8, y);
            }
        }
        assert!((table.energy(&r) - direct).abs() < 1e-12 * direct.max(1.0));
    }

    #[test]
    fn median_cut_of_a_uniform_band_splits_the_widest_way() {
        let m = map(16, 8, |_, _| 1.0);
        let table = EnergyTable::new(&m);
        let whole = TexelRect {
            x0: 0,
            y0: 0,
            x1: 16,
            y1: 8,
        };
        let (a, b) = table.median_cut(&whole);
        assert_eq!((a.x1, b.x0, a.height()), (8, 8, 8));
    }
}
