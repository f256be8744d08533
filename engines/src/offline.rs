//! Offline scene frames: the same [`SceneFrame`] the daemon builds live, made from a scene file,
//! so that `relightd render`, `relightd bench` and the tests measure exactly what runs live.

use std::sync::Arc;

use glam::Vec3;
use relight_core::scene::Scene;
use relight_core::srgb::{linear_to_srgb, srgb_to_linear};
use relight_core::{Frame, Image, PixelFormat, Timestamp};

use crate::engine::SceneFrame;
use crate::reference::{
    ReferenceError, ReferenceImages, ReferenceRenderer, ReferenceSettings, render_reference,
};

/// Where a reference samples each pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sampling {
    /// At the pixel's centre, as one engine frame samples it, so silhouettes agree pixel for
    /// pixel: what a live (changing) frame is judged against.
    Centre,
    /// Over the pixel's area, as a camera integrates it: what an engine's still frames converge
    /// to as they accumulate sub-pixel samples (`Deferred`'s accumulation).
    Area,
}

/// Which light a reference carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transport {
    /// Every bounce (up to the reference's `max_bounces`): the truth.
    Full,
    /// The lights' direct light at the first surface a camera ray meets, and emission
    /// (`max_bounces` 0): the reference's direct term, whose visibility the engines' shadow
    /// maps approximate. The full reference less this is its indirect term.
    Direct,
}

/// What the engines are judged against: the reference with full light transport, `spp` samples
/// at pixel centres (as the engines' rasteriser samples, so silhouettes agree pixel for pixel).
pub fn reference(
    scene: &Scene,
    width: u32,
    height: u32,
    spp: u32,
) -> Result<ReferenceImages, ReferenceError> {
    render_reference(
        scene,
        reference_settings(width, height, spp, Sampling::Centre, Transport::Full),
    )
}

/// The reference, progressive: samples are added until its noise is small enough (the bench
/// refines it against the best engine's error).
pub fn reference_renderer(
    scene: &Scene,
    width: u32,
    height: u32,
    sampling: Sampling,
    transport: Transport,
) -> Result<ReferenceRenderer, ReferenceError> {
    ReferenceRenderer::new(
        scene,
        reference_settings(width, height, 0, sampling, transport),
    )
}

/// The reference's settings for a picture at `width` × `height`, `spp` samples sampled so, with
/// `transport`'s bounces.
pub fn reference_settings(
    width: u32,
    height: u32,
    spp: u32,
    sampling: Sampling,
    transport: Transport,
) -> ReferenceSettings {
    let defaults = ReferenceSettings::default();
    ReferenceSettings {
        spp,
        pixel_jitter: sampling == Sampling::Area,
        size: Some((width, height)),
        max_bounces: match transport {
            Transport::Full => defaults.max_bounces,
            Transport::Direct => 0,
        },
        ..defaults
    }
}

/// The reference's own noise in the metric of [`delta_error`]: √(Σ σ²) / ‖Δ_ref‖₂ over real
/// pixels, σ each pixel's standard error of Δ. An engine scored against it reads about
/// √(e² + noise²) for a true error e, so a row is only meaningful where its error is well above
/// this.
pub fn reference_noise(reference: &ReferenceImages) -> f64 {
    let (mut variance, mut norm) = (0.0f64, 0.0f64);
    for ((se, d), on_object) in reference
        .delta_std_error
        .iter()
        .zip(&reference.delta)
        .zip(&reference.virtual_mask)
    {
        if !on_object {
            variance += f64::from(se.length_squared());
            norm += f64::from(d.length_squared());
        }
    }
    (variance / norm.max(1e-30)).sqrt()
}

/// The camera image of an offline scene: the reference's L^μ, sRGB-encoded and clipped, as a
/// camera without tone curve would record it.
pub fn background(reference: &ReferenceImages) -> Image {
    srgb_image(reference.width, reference.height, &reference.l_mu)
}

/// Linear RGB pixels (row-major) as an 8-bit sRGB image, clipped.
pub fn srgb_image(width: u32, height: u32, linear: &[Vec3]) -> Image {
    let mut image = Image::new(width, height, PixelFormat::Rgb8);
    if let Some(px) = image.as_u8_mut() {
        for (rgb, l) in px.chunks_exact_mut(3).zip(linear) {
            for (c, v) in rgb.iter_mut().zip(l.to_array()) {
                *c = linear_to_srgb(v);
            }
        }
    }
    image
}

/// A scene frame of `scene` over `background` (its size is the render size).
pub fn scene_frame(scene: Arc<Scene>, background: Image) -> SceneFrame {
    let stamp = Timestamp::new(0, 0);
    SceneFrame {
        stamp,
        seq: 0,
        color: Some(Arc::new(Frame::new(0, stamp, background))),
        depth: None,
        scene: Some(scene),
    }
}

/// Δ of a [`RelitFrame`](crate::RelitFrame) (Rgba16F) as linear RGB per pixel; empty for other
/// formats.
pub fn delta_pixels(delta: &Image) -> Vec<Vec3> {
    let Some(bits) = delta
        .as_u16()
        .filter(|_| delta.format() == PixelFormat::Rgba16F)
    else {
        return Vec::new();
    };
    bits.chunks_exact(4)
        .map(|px| {
            Vec3::new(
                half::f16::from_bits(px[0]).to_f32(),
                half::f16::from_bits(px[1]).to_f32(),
                half::f16::from_bits(px[2]).to_f32(),
            )
        })
        .collect()
}

/// An 8-bit sRGB composite as linear RGB per pixel; empty for other formats.
pub fn composite_pixels(image: &Image) -> Vec<Vec3> {
    let Some(px) = image
        .as_u8()
        .filter(|_| image.format() == PixelFormat::Rgb8)
    else {
        return Vec::new();
    };
    px.chunks_exact(3)
        .map(|c| {
            Vec3::new(
                srgb_to_linear(c[0]),
                srgb_to_linear(c[1]),
                srgb_to_linear(c[2]),
            )
        })
        .collect()
}

/// The error every engine is judged by: ‖Δ − Δ_ref‖₂ / ‖Δ_ref‖₂ over real pixels (where the
/// reference's camera ray hits no virtual object), and max |Δ − Δ_ref| there. A missing or
/// mis-sized Δ is an error of NaN.
pub fn delta_error(delta: &[Vec3], reference: &[Vec3], virtual_mask: &[bool]) -> (f64, f64) {
    if delta.len() != reference.len() {
        return (f64::NAN, f64::NAN);
    }
    let (mut err, mut norm, mut max_abs) = (0.0f64, 0.0f64, 0.0f64);
    for ((d, r), v) in delta.iter().zip(reference).zip(virtual_mask) {
        if *v {
            continue;
        }
        let e = *d - *r;
        err += f64::from(e.length_squared());
        norm += f64::from(r.length_squared());
        max_abs = max_abs.max(f64::from(e.abs().max_element()));
    }
    ((err / norm.max(1e-30)).sqrt(), max_abs)
}

/// The composite judged on the virtual object's own pixels (where the reference's camera ray
/// hits the object): ‖C − min(L^ρ_ref, 1)‖₂ / ‖min(L^ρ_ref, 1)‖₂, with C the 8-bit composite
/// decoded from sRGB and the reference clipped as that composite is. Δ on real pixels cannot
/// see an object drawn wrong; this can. `None` when the object covers no pixel or the composite
/// is missing, mis-sized or not 8-bit RGB.
pub fn object_error(composite: &Image, l_rho: &[Vec3], virtual_mask: &[bool]) -> Option<f64> {
    let linear = composite_pixels(composite);
    if linear.len() != l_rho.len() || virtual_mask.len() != l_rho.len() {
        return None;
    }
    let (mut err, mut norm, mut pixels) = (0.0f64, 0.0f64, 0usize);
    for ((c, r), _) in linear
        .iter()
        .zip(l_rho)
        .zip(virtual_mask)
        .filter(|(_, on_object)| **on_object)
    {
        let r = r.clamp(Vec3::ZERO, Vec3::ONE);
        err += f64::from((*c - r).length_squared());
        norm += f64::from(r.length_squared());
        pixels += 1;
    }
    (pixels > 0).then(|| (err / norm.max(1e-30)).sqrt())
}

/// Rec. 709 luminance of linear RGB.
fn luminance(v: Vec3) -> f32 {
    0.2126 * v.x + 0.7152 * v.y + 0.0722 * v.z
}

/// How many standard errors from zero the reference's Δ must be for a pixel to count as changed.
const SIGNIFICANT_SIGMAS: f32 = 3.0;

/// The real pixels the reference says the object changes, and how: its **shadow**, where Δ's
/// luminance is below −3 standard errors of the reference (the object takes light away), and
/// its **bleeding**, where it is above +3 (the object reflects light there). Pixels within noise
/// of zero are in neither; virtual pixels in neither.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Regions {
    pub shadow: Vec<bool>,
    pub bleeding: Vec<bool>,
}

pub fn regions(reference: &ReferenceImages) -> Regions {
    let (mut shadow, mut bleeding) = (Vec::new(), Vec::new());
    for ((d, se), on_object) in reference
        .delta
        .iter()
        .zip(&reference.delta_std_error)
        .zip(&reference.virtual_mask)
    {
        // The channels' errors are correlated (one path serves all three), so the luminance's
        // standard error is bounded by the weighted sum, not the root of the weighted squares.
        let threshold = SIGNIFICANT_SIGMAS * luminance(se.abs());
        let y = luminance(*d);
        let changed = !on_object && threshold.is_finite() && y.abs() > threshold && y != 0.0;
        shadow.push(changed && y < 0.0);
        bleeding.push(changed && y > 0.0);
    }
    Regions { shadow, bleeding }
}

/// ‖a − b‖₂ / ‖b‖₂ over the pixels `mask` selects; `None` on mismatched sizes or where `b` is
/// zero there (an empty mask included).
pub fn masked_relative_l2(a: &[Vec3], b: &[Vec3], mask: &[bool]) -> Option<f64> {
    if a.len() != b.len() || b.len() != mask.len() {
        return None;
    }
    let (mut err, mut norm) = (0.0f64, 0.0f64);
    for ((x, y), _) in a.iter().zip(b).zip(mask).filter(|(_, m)| **m) {
        err += f64::from((*x - *y).length_squared());
        norm += f64::from(y.length_squared());
    }
    (norm > 0.0).then(|| (err / norm).sqrt())
}

/// Which of an engine's two terms its error comes from, each measured by swapping the other
/// for the reference's: `direct` is the error left with the reference's indirect term in place
/// of the engine's (what its direct light, the shadow maps' visibility, gets wrong), `indirect`
/// the error left with the reference's direct term in place of the engine's (what its indirect
/// light gets wrong). Each is ‖swapped − full_ref‖₂ / ‖full_ref‖₂ over the pixels `mask`
/// selects, as the engine's own error is; the two parts of that error may cancel or add, so
/// they need not sum to it in quadrature.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TermErrors {
    pub direct: f64,
    pub indirect: f64,
}

/// [`TermErrors`] from the engine's picture with both terms (`full`) and with its direct term
/// alone (`direct`), and the reference's with every bounce (`full_ref`) and with none
/// (`direct_ref`, [`Transport::Direct`]); the indirect terms are the differences. `clip` clips
/// every picture to [0, 1] first, as an 8-bit composite is (the object's pixels, as
/// [`object_error`] judges them). `None` on mismatched sizes or where the reference is zero
/// over the mask.
pub fn term_errors(
    full: &[Vec3],
    direct: &[Vec3],
    full_ref: &[Vec3],
    direct_ref: &[Vec3],
    mask: &[bool],
    clip: bool,
) -> Option<TermErrors> {
    let n = full_ref.len();
    if [full.len(), direct.len(), direct_ref.len(), mask.len()] != [n; 4] {
        return None;
    }
    let shown = |v: Vec3| {
        if clip {
            v.clamp(Vec3::ZERO, Vec3::ONE)
        } else {
            v
        }
    };
    let swapped = |pick: fn(Vec3, Vec3, Vec3, Vec3) -> Vec3| -> Vec<Vec3> {
        (0..n)
            .map(|i| shown(pick(full[i], direct[i], full_ref[i], direct_ref[i])))
            .collect()
    };
    let truth: Vec<Vec3> = full_ref.iter().map(|&v| shown(v)).collect();
    // The engine's direct term with the reference's indirect one, and the reference's direct
    // term with the engine's indirect one.
    let reference_indirect = swapped(|_, d, r, r0| d + (r - r0));
    let reference_direct = swapped(|f, d, _, r0| r0 + (f - d));
    Some(TermErrors {
        direct: masked_relative_l2(&reference_indirect, &truth, mask)?,
        indirect: masked_relative_l2(&reference_direct, &truth, mask)?,
    })
}

/// Δ's error in the object's shadow and in its bleeding ([`Regions`]), each ‖Δ − Δ_ref‖₂ /
/// ‖Δ_ref‖₂ over its pixels: `None` where the reference has no such pixel (an object that casts
/// no visible shadow, a dark object that bleeds nothing) or Δ is missing or mis-sized.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct RegionErrors {
    pub shadow_relative_l2: Option<f64>,
    pub bleeding_relative_l2: Option<f64>,
    pub shadow_pixels: usize,
    pub bleeding_pixels: usize,
}

pub fn region_errors(delta: &[Vec3], reference: &ReferenceImages) -> RegionErrors {
    let regions = regions(reference);
    let count = |mask: &[bool]| mask.iter().filter(|m| **m).count();
    let error = |mask: &[bool]| masked_relative_l2(delta, &reference.delta, mask);
    RegionErrors {
        shadow_relative_l2: error(&regions.shadow),
        bleeding_relative_l2: error(&regions.bleeding),
        shadow_pixels: count(&regions.shadow),
        bleeding_pixels: count(&regions.bleeding),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn object_error_compares_the_composite_with_the_clipped_reference_on_object_pixels() {
        let l_rho = vec![Vec3::splat(0.5), Vec3::splat(4.0), Vec3::splat(0.2)];
        let mask = [true, true, false];
        // The object drawn exactly (8-bit), a real pixel far off: no error on the object.
        let exact = srgb_image(3, 1, &[Vec3::splat(0.5), Vec3::ONE, Vec3::ZERO]);
        let error = object_error(&exact, &l_rho, &mask).unwrap();
        assert!(error < 0.01, "{error}");
        // The object drawn black: an error of 1.
        let black = srgb_image(3, 1, &[Vec3::ZERO; 3]);
        let error = object_error(&black, &l_rho, &mask).unwrap();
        assert!((error - 1.0).abs() < 1e-6, "{error}");
        assert_eq!(object_error(&black, &l_rho, &[false; 3]), None);
        assert_eq!(object_error(&black, &l_rho[..2], &mask[..2]), None);
    }

    fn reference_of(
        delta: Vec<Vec3>,
        std_error: Vec<Vec3>,
        virtual_mask: Vec<bool>,
    ) -> ReferenceImages {
        let n = delta.len();
        ReferenceImages {
            width: n as u32,
            height: 1,
            spp: 64,
            l_rho: vec![Vec3::ZERO; n],
            l_mu: vec![Vec3::ZERO; n],
            delta,
            delta_std_error: std_error,
            l_rho_std_error: vec![Vec3::ZERO; n],
            virtual_mask,
        }
    }

    #[test]
    fn swapping_a_term_for_the_references_leaves_the_others_error() {
        let (direct_ref, indirect_ref) = (Vec3::new(-0.4, -0.4, -0.4), Vec3::splat(0.1));
        let full_ref = vec![direct_ref + indirect_ref; 4];
        let direct_refs = vec![direct_ref; 4];
        let mask = [true, true, false, true];
        let errors = |full: Vec3, direct: Vec3| {
            term_errors(
                &[full; 4],
                &[direct; 4],
                &full_ref,
                &direct_refs,
                &mask,
                false,
            )
            .unwrap()
        };
        let norm = f64::from((direct_ref + indirect_ref).length());
        // Exact: both parts 0.
        let exact = errors(direct_ref + indirect_ref, direct_ref);
        assert!(exact.direct < 1e-6 && exact.indirect < 1e-6, "{exact:?}");
        // The direct light exact, no indirect light: the indirect term is all of the error.
        let no_indirect = errors(direct_ref, direct_ref);
        assert!(no_indirect.direct < 1e-6, "{no_indirect:?}");
        assert!((no_indirect.indirect - f64::from(indirect_ref.length()) / norm).abs() < 1e-6);
        // The indirect light exact, the shadow missing: the direct term is all of it.
        let no_shadow = errors(indirect_ref, Vec3::ZERO);
        assert!((no_shadow.direct - f64::from(direct_ref.length()) / norm).abs() < 1e-6);
        assert!(no_shadow.indirect < 1e-6, "{no_shadow:?}");
        // Clipped as a composite is: a term that only overshoots 1 costs nothing.
        let bright_ref = vec![Vec3::splat(1.2); 4];
        let clipped = term_errors(
            &[Vec3::splat(3.0); 4],
            &[Vec3::splat(2.0); 4],
            &bright_ref,
            &bright_ref,
            &mask,
            true,
        )
        .unwrap();
        assert_eq!((clipped.direct, clipped.indirect), (0.0, 0.0));
        assert_eq!(
            term_errors(&[], &[], &full_ref, &direct_refs, &mask, false),
            None
        );
    }

    #[test]
    fn regions_are_where_the_reference_changes_significantly() {
        let reference = reference_of(
            vec![
                Vec3::splat(-0.5),  // shadow
                Vec3::splat(0.3),   // bleeding
                Vec3::splat(-0.01), // within 3σ of zero: neither
                Vec3::ZERO,         // untouched
                Vec3::splat(-0.5),  // on the object: neither
                Vec3::splat(-0.2),  // shadow
            ],
            vec![Vec3::splat(0.01); 6],
            vec![false, false, false, false, true, false],
        );
        let regions = regions(&reference);
        assert_eq!(regions.shadow, [true, false, false, false, false, true]);
        assert_eq!(regions.bleeding, [false, true, false, false, false, false]);

        // Half the shadow's depth everywhere, the bleeding exact, noise elsewhere.
        let delta = vec![
            Vec3::splat(-0.25),
            Vec3::splat(0.3),
            Vec3::splat(0.5),
            Vec3::splat(0.5),
            Vec3::ZERO,
            Vec3::splat(-0.1),
        ];
        let errors = region_errors(&delta, &reference);
        assert!(
            (errors.shadow_relative_l2.unwrap() - 0.5).abs() < 1e-6,
            "{errors:?}"
        );
        assert_eq!(errors.bleeding_relative_l2, Some(0.0));
        assert_eq!((errors.shadow_pixels, errors.bleeding_pixels), (2, 1));
        assert_eq!(
            region_errors(&delta[..2], &reference).shadow_relative_l2,
            None
        );

        // A reference too noisy to say (∞ standard error below 2 spp) has no regions.
        let noisy = reference_of(vec![Vec3::splat(-0.5)], vec![Vec3::INFINITY], vec![false]);
        assert_eq!(
            region_errors(&[Vec3::ZERO], &noisy),
            RegionErrors::default()
        );
    }
}
