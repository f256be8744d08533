//! A small renderer of printed planar targets (tags, boards) as a calibrated camera sees them,
//! for testing detectors and pose estimation against known truth.
//!
//! Each pixel averages `supersampling²` rays through the full [`CameraModel`] (so lens
//! distortion bends straight edges as it does on a real sensor) against textured planes, nearest
//! hit first; then image-space occluders are painted, the radiance is blurred by a Gaussian
//! (defocus and lens softness), encoded to 8 bits (linear or sRGB) and Gaussian read noise is
//! added per channel. Everything is a pure function of its inputs and the seed.
//!
//! Rays are only traced inside the projected bounding boxes of the textured planes; elsewhere
//! the image is the background, which keeps a 640 × 480 render of a tag well under a second in
//! a debug build.

use glam::{DVec2, DVec3};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_pcg::Pcg64Mcg;
use relight_core::camera::{CameraModel, gl_from_optical};
use relight_core::srgb::linear_to_srgb;
use relight_core::{Image, PixelFormat};

use super::pose::{CAMERA_FROM_OPTICAL, DPose};
use super::tag36h11::{TAG_TOTAL_CELLS, tag36h11_cells};

/// A square fiducial's cell pattern as printed: row-major, row 0 at the top, `true` = white.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TagBitmap {
    /// Cells per side of the whole pattern.
    pub total_cells: u32,
    /// Cells per side of the square whose edge is the tag's size (the square a detector reports
    /// the corners of), centred in the pattern.
    pub size_cells: u32,
    pub cells: Vec<bool>,
}

impl TagBitmap {
    /// `tag36h11` id `id` from the simulator's code table (10 × 10 cells with a white quiet
    /// zone; the size is the 8-cell black square).
    pub fn tag36h11(id: u32) -> Option<Self> {
        let rows = tag36h11_cells(id)?;
        Some(Self {
            total_cells: TAG_TOTAL_CELLS,
            size_cells: TAG_TOTAL_CELLS - 2,
            cells: rows.iter().flatten().copied().collect(),
        })
    }

    /// The cell at column `col`, row `row` (row 0 at the top).
    pub fn white_at(&self, col: u32, row: u32) -> bool {
        self.cells
            .get(row as usize * self.total_cells as usize + col as usize)
            .copied()
            .unwrap_or(true)
    }
}

/// Reflectance samples over a `width_m × height_m` rectangle centred on the origin of the plane
/// z = 0 of its own frame (+x right, +y up; texel row 0 at the top, +y).
#[derive(Debug, Clone, PartialEq)]
pub struct PlanarTexture {
    width: u32,
    height: u32,
    texels: Vec<f32>,
    width_m: f64,
    height_m: f64,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    #[error("texture of {width}×{height} texels needs {expected} values, got {actual}")]
    TextureSize {
        width: u32,
        height: u32,
        expected: usize,
        actual: usize,
    },
    #[error("render setting `{setting}` {reason}")]
    Setting {
        setting: &'static str,
        reason: String,
    },
    #[error("camera: {0}")]
    Camera(#[from] relight_core::camera::CameraError),
}

impl PlanarTexture {
    pub fn new(
        width: u32,
        height: u32,
        texels: Vec<f32>,
        width_m: f64,
        height_m: f64,
    ) -> Result<Self, RenderError> {
        let expected = width as usize * height as usize;
        if texels.len() != expected || expected == 0 {
            return Err(RenderError::TextureSize {
                width,
                height,
                expected,
                actual: texels.len(),
            });
        }
        if !(width_m.is_finite() && height_m.is_finite() && width_m > 0.0 && height_m > 0.0) {
            return Err(RenderError::Setting {
                setting: "texture size",
                reason: format!("{width_m} × {height_m} m is not a positive size"),
            });
        }
        Ok(Self {
            width,
            height,
            texels,
            width_m,
            height_m,
        })
    }

    /// A tag printed with its detected square `size_m` wide, on paper extending `margin_cells`
    /// cells beyond its pattern (families whose outer ring carries data need ≥ 1 cell of white
    /// around it). One texel per cell; the tag's centre is the texture's origin.
    pub fn tag(bitmap: &TagBitmap, size_m: f64, margin_cells: u32, white: f32, black: f32) -> Self {
        let side = bitmap.total_cells + 2 * margin_cells;
        let cell_m = size_m / f64::from(bitmap.size_cells);
        let texels = (0..side)
            .flat_map(|row| (0..side).map(move |col| (col, row)))
            .map(|(col, row)| {
                let inside = |c: u32| {
                    c.checked_sub(margin_cells)
                        .filter(|&c| c < bitmap.total_cells)
                };
                let white_cell = match (inside(col), inside(row)) {
                    (Some(c), Some(r)) => bitmap.white_at(c, r),
                    _ => true,
                };
                if white_cell { white } else { black }
            })
            .collect();
        let extent_m = f64::from(side) * cell_m;
        Self {
            width: side,
            height: side,
            texels,
            width_m: extent_m,
            height_m: extent_m,
        }
    }

    /// A uniform rectangle (an occluding card, a blank board).
    pub fn uniform(width_m: f64, height_m: f64, reflectance: f32) -> Result<Self, RenderError> {
        Self::new(1, 1, vec![reflectance], width_m, height_m)
    }

    pub fn size_m(&self) -> DVec2 {
        DVec2::new(self.width_m, self.height_m)
    }

    /// Reflectance at a point of the plane (nearest texel), `None` off the texture.
    pub fn reflectance_at(&self, point: DVec2) -> Option<f32> {
        let u = (point.x / self.width_m + 0.5) * f64::from(self.width);
        let v = (0.5 - point.y / self.height_m) * f64::from(self.height);
        if !(u >= 0.0 && v >= 0.0 && u < f64::from(self.width) && v < f64::from(self.height)) {
            return None;
        }
        self.texels
            .get(v as usize * self.width as usize + u as usize)
            .copied()
    }
}

/// A textured plane placed in front of the camera.
#[derive(Debug, Clone, PartialEq)]
pub struct Surface {
    /// The texture's frame in relight's camera frame (glTF convention, as
    /// `MarkerDetection::camera_from_marker`). The print faces +z of this frame; seen from
    /// behind it shows the background.
    pub camera_from_surface: DPose,
    pub texture: PlanarTexture,
}

/// A rectangle painted over the image (in pixels, inclusive of the pixels whose centres it
/// covers) after the planes and before blur: a finger, a cable, a cup in front of a tag.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Occluder {
    pub min_px: DVec2,
    pub max_px: DVec2,
    pub radiance: f32,
}

/// How stored radiance becomes 8-bit code values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    /// code = 255 · radiance (a linear machine-vision camera).
    Linear,
    /// IEC 61966-2-1 (a webcam).
    Srgb,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderSettings {
    /// Radiance of everything that is not a print (0–1 of full scale).
    pub background: f32,
    /// Radiance of a print = reflectance × illumination.
    pub illumination: f32,
    /// Rays per pixel along each axis.
    pub supersampling: u32,
    /// Standard deviation of the Gaussian blur, pixels (0: none).
    pub blur_sigma_px: f64,
    /// Standard deviation of the read noise, 8-bit code values (0: none).
    pub noise_sigma: f64,
    pub seed: u64,
    /// `Rgb8` (grey) or `Mono8`.
    pub format: PixelFormat,
    pub encoding: Encoding,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            background: 0.5,
            illumination: 1.0,
            supersampling: 4,
            blur_sigma_px: 0.0,
            noise_sigma: 0.0,
            seed: 1,
            format: PixelFormat::Rgb8,
            encoding: Encoding::Linear,
        }
    }
}

/// Samples per edge when bounding a plane's image (the image of a straight edge curves under
/// distortion).
const OUTLINE_SAMPLES: u32 = 32;

/// Renders `surfaces` as `camera` sees them.
pub fn render(
    camera: &CameraModel,
    surfaces: &[Surface],
    occluders: &[Occluder],
    settings: &RenderSettings,
) -> Result<Image, RenderError> {
    camera.validate()?;
    let bad = |setting, reason: &str| {
        Err(RenderError::Setting {
            setting,
            reason: reason.into(),
        })
    };
    if settings.supersampling == 0 || settings.supersampling > 64 {
        return bad("supersampling", "must be 1–64");
    }
    if !(settings.blur_sigma_px.is_finite() && settings.blur_sigma_px >= 0.0) {
        return bad("blur_sigma_px", "must be ≥ 0");
    }
    if !(settings.noise_sigma.is_finite() && settings.noise_sigma >= 0.0) {
        return bad("noise_sigma", "must be ≥ 0");
    }
    if !matches!(settings.format, PixelFormat::Rgb8 | PixelFormat::Mono8) {
        return bad("format", "must be rgb8 or mono8");
    }
    let (width, height) = (camera.width() as usize, camera.height() as usize);
    let mut radiance = vec![settings.background; width * height];

    let surface_from_camera: Vec<DPose> = surfaces
        .iter()
        .map(|s| s.camera_from_surface.inverse())
        .collect();
    let n = settings.supersampling;
    let weight = 1.0 / (n * n) as f32;
    for (x0, y0, x1, y1) in surfaces
        .iter()
        .filter_map(|surface| pixel_bounds(camera, surface))
        .collect::<Vec<_>>()
    {
        for y in y0..=y1 {
            for x in x0..=x1 {
                let mut sum = 0.0;
                for s in 0..n * n {
                    let offset = DVec2::new(
                        (f64::from(s % n) + 0.5) / f64::from(n) - 0.5,
                        (f64::from(s / n) + 0.5) / f64::from(n) - 0.5,
                    );
                    let pixel = DVec2::new(x as f64, y as f64) + offset;
                    sum += camera
                        .unproject(pixel)
                        .and_then(|ray| trace(gl_from_optical(ray), surfaces, &surface_from_camera))
                        .map_or(settings.background, |r| r * settings.illumination);
                }
                radiance[y * width + x] = sum * weight;
            }
        }
    }
    for occluder in occluders {
        let lo = occluder.min_px.max(DVec2::ZERO).ceil();
        let hi = occluder
            .max_px
            .min(DVec2::new(width as f64 - 1.0, height as f64 - 1.0))
            .floor();
        if lo.x > hi.x || lo.y > hi.y {
            continue;
        }
        for y in lo.y as usize..=hi.y as usize {
            radiance[y * width..(y + 1) * width][lo.x as usize..=hi.x as usize]
                .fill(occluder.radiance);
        }
    }
    if settings.blur_sigma_px > 0.0 {
        gaussian_blur(&mut radiance, width, height, settings.blur_sigma_px);
    }

    let mut image = Image::new(camera.width(), camera.height(), settings.format);
    let channels = settings.format.channels();
    let mut rng = Pcg64Mcg::seed_from_u64(settings.seed);
    let noise =
        Normal::new(0.0, settings.noise_sigma.max(1e-300)).map_err(|e| RenderError::Setting {
            setting: "noise_sigma",
            reason: e.to_string(),
        })?;
    let Some(codes) = image.as_u8_mut() else {
        return bad("format", "must be rgb8 or mono8");
    };
    for (pixel, value) in codes.chunks_exact_mut(channels).zip(&radiance) {
        let encoded = match settings.encoding {
            Encoding::Linear => f64::from(value.clamp(0.0, 1.0)) * 255.0,
            Encoding::Srgb => f64::from(linear_to_srgb(*value)),
        };
        for code in pixel {
            let noisy = if settings.noise_sigma > 0.0 {
                encoded + noise.sample(&mut rng)
            } else {
                encoded
            };
            *code = noisy.round().clamp(0.0, 255.0) as u8;
        }
    }
    Ok(image)
}

/// Reflectance of the nearest print a ray (glTF camera frame, from the camera centre) meets.
fn trace(ray: DVec3, surfaces: &[Surface], surface_from_camera: &[DPose]) -> Option<f32> {
    let mut nearest: Option<(f64, f32)> = None;
    for (surface, from_camera) in surfaces.iter().zip(surface_from_camera) {
        let origin = from_camera.translation;
        let dir = from_camera.transform_vector(ray);
        // The print faces +z: a ray that sees its front travels towards −z.
        if dir.z >= -1e-12 {
            continue;
        }
        let t = -origin.z / dir.z;
        if t <= 0.0 || nearest.is_some_and(|(best, _)| best <= t) {
            continue;
        }
        if let Some(r) = surface
            .texture
            .reflectance_at((origin + dir * t).truncate())
        {
            nearest = Some((t, r));
        }
    }
    nearest.map(|(_, r)| r)
}

/// Pixel rectangle (inclusive) that can see `surface`, from its projected outline plus a
/// two-pixel margin; `None` when no part of it projects into the image.
fn pixel_bounds(camera: &CameraModel, surface: &Surface) -> Option<(usize, usize, usize, usize)> {
    let optical_from_surface = CAMERA_FROM_OPTICAL * surface.camera_from_surface;
    let half = surface.texture.size_m() / 2.0;
    let corners = [
        DVec2::new(-half.x, -half.y),
        DVec2::new(half.x, -half.y),
        DVec2::new(half.x, half.y),
        DVec2::new(-half.x, half.y),
    ];
    let mut lo = DVec2::splat(f64::INFINITY);
    let mut hi = DVec2::splat(f64::NEG_INFINITY);
    for k in 0..4 {
        let (a, b) = (corners[k], corners[(k + 1) % 4]);
        for s in 0..OUTLINE_SAMPLES {
            let point = a.lerp(b, f64::from(s) / f64::from(OUTLINE_SAMPLES));
            let Some(pixel) =
                camera.project(optical_from_surface.transform_point(point.extend(0.0)))
            else {
                // Part of the plane is outside the valid field: trace the whole image.
                return Some((
                    0,
                    0,
                    camera.width() as usize - 1,
                    camera.height() as usize - 1,
                ));
            };
            lo = lo.min(pixel);
            hi = hi.max(pixel);
        }
    }
    let max = DVec2::new(
        f64::from(camera.width()) - 1.0,
        f64::from(camera.height()) - 1.0,
    );
    let lo = (lo - 2.0).floor().max(DVec2::ZERO);
    let hi = (hi + 2.0).ceil().min(max);
    (lo.x <= hi.x && lo.y <= hi.y).then_some((
        lo.x as usize,
        lo.y as usize,
        hi.x as usize,
        hi.y as usize,
    ))
}

/// Separable Gaussian blur (kernel to ±3σ, edges clamped), in place.
fn gaussian_blur(values: &mut [f32], width: usize, height: usize, sigma: f64) {
    let radius = (3.0 * sigma).ceil() as usize;
    let kernel: Vec<f32> = (0..=2 * radius)
        .map(|i| {
            let d = i as f64 - radius as f64;
            (-0.5 * d * d / (sigma * sigma)).exp() as f32
        })
        .collect();
    let total: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / total).collect();
    let mut scratch = vec![0.0f32; values.len()];
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    for y in 0..height {
        for x in 0..width {
            scratch[y * width + x] = kernel
                .iter()
                .enumerate()
                .map(|(k, w)| {
                    w * values[y * width + clamp(x as isize + k as isize - radius as isize, width)]
                })
                .sum();
        }
    }
    for y in 0..height {
        for x in 0..width {
            values[y * width + x] = kernel
                .iter()
                .enumerate()
                .map(|(k, w)| {
                    w * scratch
                        [clamp(y as isize + k as isize - radius as isize, height) * width + x]
                })
                .sum();
        }
    }
}

/// Pixels of points of an object at `camera_from_object` (glTF camera frame); `None` when one
/// does not project.
pub fn project_points(
    camera: &CameraModel,
    camera_from_object: &DPose,
    points_in_object: &[DVec3],
) -> Option<Vec<DVec2>> {
    let optical_from_object = CAMERA_FROM_OPTICAL * *camera_from_object;
    points_in_object
        .iter()
        .map(|p| camera.project(optical_from_object.transform_point(*p)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;
    use relight_core::camera::Pinhole;

    fn camera() -> CameraModel {
        CameraModel::Pinhole(Pinhole {
            width: 160,
            height: 120,
            fx: 150.0,
            fy: 150.0,
            cx: 79.5,
            cy: 59.5,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        })
    }

    fn black_square(size_m: f64, camera_from_surface: DPose) -> Surface {
        Surface {
            camera_from_surface,
            texture: PlanarTexture::uniform(size_m, size_m, 0.0).unwrap(),
        }
    }

    fn darkness(image: &Image) -> f64 {
        image
            .as_u8()
            .unwrap()
            .iter()
            .step_by(image.format().channels())
            .map(|&c| 1.0 - f64::from(c) / 255.0)
            .sum()
    }

    #[test]
    fn antialiased_coverage_matches_the_projected_area() {
        // A 0.1 m square 1 m ahead, rotated in plane so its edges cut pixels at all phases.
        let pose = DPose::new(DQuat::from_rotation_z(0.3), DVec3::new(0.013, -0.007, -1.0));
        let settings = RenderSettings {
            background: 1.0,
            supersampling: 8,
            ..RenderSettings::default()
        };
        let image = render(&camera(), &[black_square(0.1, pose)], &[], &settings).unwrap();
        let expected_px2 = (0.1 * 150.0f64).powi(2);
        let measured = darkness(&image);
        assert!(
            (measured / expected_px2 - 1.0).abs() < 0.01,
            "{measured} vs {expected_px2}"
        );
        // Blur moves darkness around but keeps it.
        let blurred = render(
            &camera(),
            &[black_square(0.1, pose)],
            &[],
            &RenderSettings {
                blur_sigma_px: 1.5,
                ..settings
            },
        )
        .unwrap();
        assert!((darkness(&blurred) / measured - 1.0).abs() < 0.01);
    }

    #[test]
    fn prints_seen_from_behind_and_occluders_show_what_is_in_front() {
        let facing_away = DPose::new(DQuat::from_rotation_y(3.0), DVec3::new(0.0, 0.0, -1.0));
        let settings = RenderSettings {
            background: 1.0,
            supersampling: 1,
            ..RenderSettings::default()
        };
        let image = render(&camera(), &[black_square(0.2, facing_away)], &[], &settings).unwrap();
        assert_eq!(darkness(&image), 0.0);
        let occluder = Occluder {
            min_px: DVec2::new(10.0, 20.0),
            max_px: DVec2::new(19.0, 24.0),
            radiance: 0.0,
        };
        let image = render(&camera(), &[], &[occluder], &settings).unwrap();
        assert_eq!(darkness(&image), 50.0);
        // A nearer plane hides a farther one.
        let near = black_square(
            0.05,
            DPose::new(DQuat::IDENTITY, DVec3::new(0.0, 0.0, -0.5)),
        );
        let far = Surface {
            camera_from_surface: DPose::new(DQuat::IDENTITY, DVec3::new(0.0, 0.0, -1.0)),
            texture: PlanarTexture::uniform(0.5, 0.5, 1.0).unwrap(),
        };
        let image = render(&camera(), &[far.clone(), near.clone()], &[], &settings).unwrap();
        let again = render(&camera(), &[near, far], &[], &settings).unwrap();
        assert_eq!(image, again);
        assert!((darkness(&image) - (0.05f64 * 300.0).powi(2)).abs() < 40.0);
    }

    #[test]
    fn noise_has_the_requested_deviation() {
        let settings = RenderSettings {
            noise_sigma: 3.0,
            format: PixelFormat::Mono8,
            ..RenderSettings::default()
        };
        let image = render(&camera(), &[], &[], &settings).unwrap();
        let codes = image.as_u8().unwrap();
        let mean = codes.iter().map(|&c| f64::from(c)).sum::<f64>() / codes.len() as f64;
        let var = codes
            .iter()
            .map(|&c| (f64::from(c) - mean).powi(2))
            .sum::<f64>()
            / codes.len() as f64;
        // Rounding adds 1/12 code² of variance.
        assert!((mean - 127.5).abs() < 0.1, "{mean}");
        assert!((var - 9.0 - 1.0 / 12.0).abs() < 0.4, "{var}");
    }

    #[test]
    fn tag_texture_reproduces_the_cells() {
        let bitmap = TagBitmap::tag36h11(3).unwrap();
        let size_m = 0.08;
        let texture = PlanarTexture::tag(&bitmap, size_m, 1, 1.0, 0.0);
        let cell = size_m / 8.0;
        assert!((texture.size_m().x - 12.0 * cell).abs() < 1e-12);
        let cells = tag36h11_cells(3).unwrap();
        for (r, row) in cells.iter().enumerate() {
            for (c, &white) in row.iter().enumerate() {
                let centre = DVec2::new((c as f64 - 4.5) * cell, (4.5 - r as f64) * cell);
                assert_eq!(
                    texture.reflectance_at(centre),
                    Some(if white { 1.0 } else { 0.0 })
                );
            }
        }
        // The paper margin is white; beyond it there is no texture.
        assert_eq!(
            texture.reflectance_at(DVec2::new(5.5 * cell, 0.0)),
            Some(1.0)
        );
        assert_eq!(texture.reflectance_at(DVec2::new(6.5 * cell, 0.0)), None);
    }

    #[test]
    fn bad_settings_are_typed_errors() {
        let cases = [
            RenderSettings {
                supersampling: 0,
                ..RenderSettings::default()
            },
            RenderSettings {
                blur_sigma_px: -1.0,
                ..RenderSettings::default()
            },
            RenderSettings {
                format: PixelFormat::DepthF32M,
                ..RenderSettings::default()
            },
        ];
        for settings in cases {
            assert!(matches!(
                render(&camera(), &[], &[], &settings),
                Err(RenderError::Setting { .. })
            ));
        }
        assert!(PlanarTexture::new(2, 2, vec![0.0; 3], 1.0, 1.0).is_err());
        assert!(PlanarTexture::uniform(0.0, 1.0, 0.5).is_err());
    }
}
