//! Invalid depth never becomes geometry: frames of zeros, NaN, ±∞ and out-of-range values go
//! through the whole chain (decode, guided filter, temporal merge, positions, normals) without
//! a panic, a NaN or a single invented point; bad inputs are errors, not panics. Also the
//! filter's exact cases: a slanted plane is reproduced, a depth step at a colour edge is kept.

use glam::{Quat, Vec3};
use relight_core::camera::Pinhole;
use relight_core::{Image, PixelFormat, Pose};
use relight_recon::depth::{
    DepthError, DepthMap, DepthRange, GeometrySource, GuidedFilterSettings, ProxySwitch,
    guided_filter,
};
use relight_recon::normals::{NormalSettings, normals, positions};
use relight_recon::temporal::{ResetReason, TemporalMerge, TemporalSettings};

const W: u32 = 32;
const H: u32 = 24;

fn camera() -> Pinhole {
    Pinhole {
        width: W,
        height: H,
        fx: 30.0,
        fy: 30.0,
        cx: f64::from(W - 1) / 2.0,
        cy: f64::from(H - 1) / 2.0,
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    }
}

fn grey(code: u8) -> Image {
    let mut image = Image::new(W, H, PixelFormat::Rgb8);
    image.as_u8_mut().unwrap().fill(code);
    image
}

fn f32_depth(values: impl Fn(usize) -> f32) -> Image {
    let mut image = Image::new(W, H, PixelFormat::DepthF32M);
    for (i, v) in image.as_f32_mut().unwrap().iter_mut().enumerate() {
        *v = values(i);
    }
    image
}

fn settings() -> GuidedFilterSettings {
    GuidedFilterSettings::kinect_v1(30.0)
}

/// Everything downstream of `image`, checked: finite, and geometry only where `image` had
/// valid depth.
fn run_chain(image: &Image, merge: &mut TemporalMerge, pose: &Pose) -> usize {
    let (raw, census) = DepthMap::from_image_with_census(image, DepthRange::default()).unwrap();
    assert_eq!(census.total(), (W * H) as usize);
    let filtered = guided_filter(&raw, &grey(128), &settings()).unwrap();
    let merged = merge.merge(&filtered, &camera(), pose).unwrap();
    let points = positions(&merged, &camera()).unwrap();
    let normal_map = normals(&points, &NormalSettings::default());
    for (i, (((r, f), m), p)) in raw
        .metres
        .iter()
        .zip(&filtered.metres)
        .zip(&merged.metres)
        .zip(&points.points_in_camera)
        .enumerate()
    {
        assert!(r.is_finite() && f.is_finite() && m.is_finite(), "pixel {i}");
        let valid = *r > 0.0;
        assert_eq!(*f > 0.0, valid, "pixel {i}: the filter keeps validity");
        assert_eq!(*m > 0.0, valid, "pixel {i}: the merge keeps validity");
        assert_eq!(
            p.is_some(),
            valid,
            "pixel {i}: a point exactly where depth is"
        );
        if let Some(p) = p {
            assert!(p.is_finite());
        }
        if let Some(n) = normal_map.normals_in_camera[i] {
            assert!(valid && n.is_finite() && (n.length() - 1.0).abs() < 1e-4);
        }
    }
    census.valid
}

#[test]
fn frames_with_no_valid_depth_make_no_geometry_and_switch_to_the_proxy() {
    let mut merge = TemporalMerge::new(TemporalSettings::kinect_v1(30.0));
    let mut switch = ProxySwitch::default();
    let pose = Pose::IDENTITY;
    let frames = [
        Image::new(W, H, PixelFormat::DepthU16Mm),
        f32_depth(|_| f32::NAN),
        f32_depth(|_| f32::INFINITY),
        f32_depth(|_| f32::NEG_INFINITY),
        f32_depth(|_| -1.0),
        f32_depth(|_| 0.2), // too near: a sensor held against the object
        f32_depth(|_| 9.0), // too far
        f32_depth(|_| f32::MAX),
        f32_depth(|_| f32::MIN_POSITIVE),
    ];
    for image in &frames {
        let (_, census) = DepthMap::from_image_with_census(image, DepthRange::default()).unwrap();
        assert_eq!(run_chain(image, &mut merge, &pose), 0);
        assert_eq!(census.valid_fraction(), 0.0);
        assert_eq!(switch.update(&census), GeometrySource::Proxy);
        assert!(merge.weights().iter().all(|w| *w == 0.0));
    }
    // Depth comes back: the switch returns to it, the merge restarts cleanly.
    let wall = f32_depth(|_| 1.5);
    let (_, census) = DepthMap::from_image_with_census(&wall, DepthRange::default()).unwrap();
    assert_eq!(run_chain(&wall, &mut merge, &pose), (W * H) as usize);
    assert_eq!(switch.update(&census), GeometrySource::Depth);
}

#[test]
fn mixed_invalid_values_are_counted_and_never_become_geometry() {
    let bad = [
        0.0,
        f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        -2.0,
        0.3,
        7.0,
    ];
    let image = f32_depth(|i| {
        if i % 3 == 0 {
            bad[(i / 3) % bad.len()]
        } else {
            1.0 + 0.001 * (i % W as usize) as f32
        }
    });
    let (_, census) = DepthMap::from_image_with_census(&image, DepthRange::default()).unwrap();
    let n = (W * H) as usize;
    let invalid = n.div_ceil(3);
    assert_eq!(census.valid, n - invalid);
    assert_eq!(
        census.missing + census.non_finite + census.too_near + census.too_far,
        invalid
    );
    assert!(
        census.non_finite > 0 && census.too_near > 0 && census.too_far > 0 && census.missing > 0
    );
    let mut merge = TemporalMerge::new(TemporalSettings::kinect_v1(30.0));
    for _ in 0..3 {
        run_chain(&image, &mut merge, &Pose::IDENTITY);
    }
    // A map whose public values were set by hand is checked too.
    let mut by_hand = DepthMap::from_image(&image, DepthRange::default()).unwrap();
    by_hand.metres[1] = f32::NAN;
    by_hand.metres[2] = -1.0;
    let filtered = guided_filter(&by_hand, &grey(100), &settings()).unwrap();
    assert_eq!(filtered.metres[1], 0.0);
    assert_eq!(filtered.metres[2], 0.0);
    assert!(filtered.metres.iter().all(|z| z.is_finite()));
}

#[test]
fn bad_inputs_are_errors() {
    let depth = DepthMap::invalid(W, H);
    assert!(matches!(
        DepthMap::from_image(&grey(1), DepthRange::default()),
        Err(DepthError::NotDepth { .. })
    ));
    assert!(matches!(
        guided_filter(
            &depth,
            &Image::new(W, H - 1, PixelFormat::Rgb8),
            &settings()
        ),
        Err(DepthError::SizeMismatch { .. })
    ));
    assert!(matches!(
        guided_filter(
            &depth,
            &Image::new(W, H, PixelFormat::DepthU16Mm),
            &settings()
        ),
        Err(DepthError::BadGuide { .. })
    ));
    for bad in [
        GuidedFilterSettings {
            eps: 0.0,
            ..settings()
        },
        GuidedFilterSettings {
            eps: f32::NAN,
            ..settings()
        },
        GuidedFilterSettings {
            max_deviation_sigmas: -1.0,
            ..settings()
        },
        GuidedFilterSettings {
            radius_px: 1000,
            ..settings()
        },
    ] {
        assert!(matches!(
            guided_filter(&depth, &grey(1), &bad),
            Err(DepthError::Setting { .. })
        ));
    }
    let short = DepthMap {
        width: W,
        height: H,
        metres: vec![1.0; 5],
    };
    assert!(matches!(
        guided_filter(&short, &grey(1), &settings()),
        Err(DepthError::BadLength { .. })
    ));
    assert!(positions(&short, &camera()).is_err());
    let mut merge = TemporalMerge::new(TemporalSettings::kinect_v1(30.0));
    assert!(merge.merge(&short, &camera(), &Pose::IDENTITY).is_err());
    let bad_merge = TemporalSettings {
        max_weight: 0.5,
        ..TemporalSettings::kinect_v1(30.0)
    };
    assert!(
        TemporalMerge::new(bad_merge)
            .merge(&depth, &camera(), &Pose::IDENTITY)
            .is_err()
    );
    assert!(
        DepthMap::from_image(
            &f32_depth(|_| 1.0),
            DepthRange {
                min_m: f32::NAN,
                max_m: 1.0
            }
        )
        .is_err()
    );
    assert!(DepthMap::from_image(&f32_depth(|_| 1.0), (3.0..=1.0).into()).is_err());
}

#[test]
fn a_non_finite_pose_restarts_the_merge() {
    let wall = DepthMap {
        width: W,
        height: H,
        metres: vec![1.5; (W * H) as usize],
    };
    let mut merge = TemporalMerge::new(TemporalSettings::kinect_v1(30.0));
    merge.merge(&wall, &camera(), &Pose::IDENTITY).unwrap();
    let broken = Pose {
        rotation: Quat::from_xyzw(f32::NAN, 0.0, 0.0, 1.0),
        translation: Vec3::ZERO,
    };
    let out = merge.merge(&wall, &camera(), &broken).unwrap();
    assert_eq!(merge.report().reset, Some(ResetReason::NonFinitePose));
    assert_eq!(out, wall);
    let out = merge.merge(&wall, &camera(), &Pose::IDENTITY).unwrap();
    assert_eq!(merge.report().reset, Some(ResetReason::NonFinitePose));
    assert_eq!(out, wall);
}

/// A surface that moved everywhere (here: the wall jumped from 1 m to 2 m under a static pose)
/// restarts the merge instead of averaging the two.
#[test]
fn a_changed_scene_is_not_averaged_with_the_old_one() {
    let at = |z: f32| DepthMap {
        width: W,
        height: H,
        metres: vec![z; (W * H) as usize],
    };
    let mut merge = TemporalMerge::new(TemporalSettings::kinect_v1(30.0));
    merge.merge(&at(1.0), &camera(), &Pose::IDENTITY).unwrap();
    merge.merge(&at(1.0), &camera(), &Pose::IDENTITY).unwrap();
    assert_eq!(merge.report().merged, (W * H) as usize);
    let out = merge.merge(&at(2.0), &camera(), &Pose::IDENTITY).unwrap();
    assert_eq!(out, at(2.0));
    assert!(
        matches!(merge.report().reset, Some(ResetReason::Disagreement { agreement }) if agreement == 0.0)
    );
}

/// A plane's disparity is affine in the pixel position, and the filter's local model contains
/// the pixel offset, so a slanted plane comes out exactly — at the borders and around holes
/// too, where a plain box mean would pull pixels towards the window's centroid.
#[test]
fn a_slanted_plane_is_reproduced_at_borders_and_holes() {
    let depth_at = |x: f32, y: f32| 1.0 / (0.5 + 0.01 * x + 0.004 * y);
    let mut metres: Vec<f32> = (0..W * H)
        .map(|i| depth_at((i % W) as f32, (i / W) as f32))
        .collect();
    for hole in [5 * W + 5, 5 * W + 6, 6 * W + 5, 12 * W + 20] {
        metres[hole as usize] = 0.0;
    }
    let depth = DepthMap {
        width: W,
        height: H,
        metres,
    };
    // A colour ramp that is not aligned with the plane's slope, so the guide has variance.
    let mut guide = Image::new(W, H, PixelFormat::Rgb8);
    for (i, px) in guide.as_u8_mut().unwrap().chunks_exact_mut(3).enumerate() {
        let (x, y) = (i as u32 % W, i as u32 / W);
        px.copy_from_slice(&[(x * 7 % 256) as u8, (y * 11 % 256) as u8, 90]);
    }
    let settings = GuidedFilterSettings {
        max_deviation_sigmas: f32::INFINITY,
        ..settings()
    };
    let filtered = guided_filter(&depth, &guide, &settings).unwrap();
    // Exact but for f32 rounding and the ε_pos shrinkage of the slope (10⁻⁴ relative).
    for (i, (f, d)) in filtered.metres.iter().zip(&depth.metres).enumerate() {
        assert!((f - d).abs() <= 1e-4 * d, "pixel {i}: {f} vs {d}");
    }
}

/// Two walls at 1 m and 1.6 m meeting at a colour edge (white / black): the colour keeps the
/// step a step; without the colour edge the deviation guard does.
#[test]
fn a_depth_step_is_kept_by_a_colour_edge_or_the_guard() {
    let left = |i: usize| (i % W as usize) < (W as usize) / 2;
    let depth = DepthMap {
        width: W,
        height: H,
        metres: (0..(W * H) as usize)
            .map(|i| if left(i) { 1.0 } else { 1.6 })
            .collect(),
    };
    let mut edge = Image::new(W, H, PixelFormat::Rgb8);
    for (i, px) in edge.as_u8_mut().unwrap().chunks_exact_mut(3).enumerate() {
        px.fill(if left(i) { 230 } else { 20 });
    }
    // A Kinect at 640 × 480 (f = 580 px): σ(1.6 m) ≈ 3.4 mm.
    let kinect = GuidedFilterSettings::kinect_v1(580.0);
    let unguarded = GuidedFilterSettings {
        max_deviation_sigmas: f32::INFINITY,
        ..kinect
    };
    let worst = |guide: &Image, settings: &GuidedFilterSettings| {
        let filtered = guided_filter(&depth, guide, settings).unwrap();
        filtered
            .metres
            .iter()
            .zip(&depth.metres)
            .map(|(f, d)| (f - d).abs())
            .fold(0.0f32, f32::max)
    };
    let step = 0.6;
    let with_edge = worst(&edge, &unguarded);
    let flat = worst(&grey(128), &unguarded);
    let flat_guarded = worst(&grey(128), &kinect);
    println!(
        "largest deviation: colour edge {with_edge} m, flat guide {flat} m, flat + guard {flat_guarded} m"
    );
    // ε shrinks the colour coefficient by ε / var(I) ≈ 2 % of the step in windows across it.
    assert!(with_edge < 0.05 * step);
    assert!(
        flat > 0.2 * step,
        "without colour the windows across the step blend it"
    );
    assert!(flat_guarded <= 3.0 * kinect.noise.sigma_m(1.6));
}
