//! `relightd render`: an offline scene (scene.toml + glTF) with the reference path tracer, or
//! with an engine judged against it.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use relight_core::frame::{Image, PixelFormat};
use relight_core::scene::Scene;
use relight_daemon::sinks::exr_out::write_exr;
use relight_daemon::sinks::png_out::{tonemap_reinhard, write_png};
use relight_engines::offline;
use relight_reference::{ReferenceImages, ReferenceRenderer, ReferenceSettings};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The scene directory (scene.toml + glTF).
    #[arg(long)]
    scene: PathBuf,
    /// `reference` (the CPU path tracer alone) or an engine, judged against the reference.
    #[arg(long, default_value = "reference", value_parser = crate::engine_or_reference())]
    engine: String,
    /// Reference samples per pixel (for another engine: of the reference it is judged
    /// against, whose L^μ is also its camera image).
    #[arg(long, default_value_t = 64)]
    spp: u32,
    /// Output directory: L^ρ, L^μ and Δ as EXR, the composite as PNG, summary.json.
    #[arg(long)]
    out: PathBuf,
    /// Override the scene camera's image size.
    #[arg(long, requires = "height")]
    width: Option<u32>,
    /// With --width: the image height.
    #[arg(long, requires = "width")]
    height: Option<u32>,
    /// Bounces after the first hit.
    #[arg(long, default_value_t = 8)]
    bounces: u32,
    /// Seeds the reference's random streams (same seed, same image).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Trace the reference through each pixel's centre instead of over its area: the
    /// reference an engine is judged against (`--engine`, `relightd bench`), so that a
    /// truncated one (`--bounces`) compares with an engine without the silhouettes' coverage.
    #[arg(long)]
    pixel_centres: bool,
    /// Engine parameters (`name=value`, repeatable), as `relightctl engine params set`.
    #[arg(long = "param")]
    params: Vec<String>,
}

pub fn run(args: Args) -> Result<()> {
    let size = args.width.zip(args.height);
    if args.engine != "reference" {
        return render_engine(&args, size);
    }
    let settings = ReferenceSettings {
        spp: args.spp,
        max_bounces: args.bounces,
        seed: args.seed,
        size,
        pixel_jitter: !args.pixel_centres,
        ..ReferenceSettings::default()
    };
    render_with_reference(&args.scene, settings, &args.out)
}

fn render_with_reference(scene_dir: &Path, settings: ReferenceSettings, out: &Path) -> Result<()> {
    let scene = Scene::load(scene_dir)?;
    let started = Instant::now();
    let mut renderer = ReferenceRenderer::new(&scene, settings)?;
    let images = trace_with_progress(&mut renderer, settings.spp);
    let seconds = started.elapsed().as_secs_f64();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let (w, h) = (images.width, images.height);
    for (name, pixels) in [
        ("l_rho", &images.l_rho),
        ("l_mu", &images.l_mu),
        ("delta", &images.delta),
        ("delta_std_error", &images.delta_std_error),
    ] {
        write_exr(&out.join(format!("{name}.exr")), w, h, pixels)?;
    }
    // Offline, the background is L^μ itself, so background + Δ on real pixels and L^ρ on
    // virtual pixels are both L^ρ.
    write_png(
        &out.join("composite.png"),
        &tonemap_reinhard(w, h, &images.l_rho),
    )?;
    write_virtual_mask(out, w, h, &images.virtual_mask)?;
    let real = images.virtual_mask.iter().filter(|v| !**v).count().max(1);
    let mean_std_error = images
        .delta_std_error
        .iter()
        .zip(&images.virtual_mask)
        .filter(|(_, v)| !**v)
        .map(|(e, _)| f64::from(e.max_element()))
        .sum::<f64>()
        / real as f64;
    let summary = serde_json::json!({
        "scene": scene.name,
        "engine": "reference",
        "width": w,
        "height": h,
        "spp": images.spp,
        "max_bounces": settings.max_bounces,
        "pixel_centres": !settings.pixel_jitter,
        "seconds": seconds,
        "mean_delta_std_error_real_pixels": mean_std_error,
    });
    std::fs::write(
        out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    println!(
        "{}: {w}×{h}, {} spp in {seconds:.2} s; mean std error of Δ on real pixels {mean_std_error:.2e}; wrote {}",
        scene.name,
        images.spp,
        out.display()
    );
    Ok(())
}

/// Which pixels are the object's, as `virtual_mask.png`: to score an image region by region
/// against the reference's images.
fn write_virtual_mask(out: &Path, w: u32, h: u32, virtual_mask: &[bool]) -> Result<()> {
    let mut mask = Image::new(w, h, PixelFormat::Mono8);
    if let Some(pixels) = mask.as_u8_mut() {
        for (pixel, object) in pixels.iter_mut().zip(virtual_mask) {
            *pixel = if *object { 255 } else { 0 };
        }
    }
    Ok(write_png(&out.join("virtual_mask.png"), &mask)?)
}

/// Trace `spp` samples per pixel in batches, with a bar on stderr when it is a terminal (a
/// 256-spp reference takes a minute on a laptop CPU).
fn trace_with_progress(renderer: &mut ReferenceRenderer, spp: u32) -> ReferenceImages {
    let bar = indicatif::ProgressBar::new(u64::from(spp)).with_style(
        indicatif::ProgressStyle::with_template(
            "reference {bar:30} {pos}/{len} spp  {elapsed} (eta {eta})",
        )
        .expect("a valid template"),
    );
    let batch = (spp / 32).max(1);
    while renderer.spp() < spp {
        renderer.add_samples(batch.min(spp - renderer.spp()));
        bar.set_position(u64::from(renderer.spp()));
    }
    bar.finish_and_clear();
    renderer.images()
}

/// Render an offline scene with a relighting engine: Δ as EXR beside the reference's Δ and L^ρ,
/// the composite and the object's mask as PNG, and a summary with the frame time and the error
/// of Δ against the reference at `--spp`, traced with `--bounces` and `--seed` (`--bounces 0`:
/// the engine against direct light alone).
fn render_engine(args: &Args, size: Option<(u32, u32)>) -> Result<()> {
    let (engine, spp, out) = (args.engine.as_str(), args.spp, args.out.as_path());
    let scene = Arc::new(Scene::load(&args.scene)?);
    let (w, h) = size.unwrap_or((scene.camera.width, scene.camera.height));
    // One frame as a live, changing frame draws it (pixel centres), scored against the
    // reference sampled so: the warm-up frame before the timed one would otherwise count as
    // a still frame accumulated into it. `bench` measures the accumulation.
    let registry = relight_engines::EngineRegistry::new();
    let mut params = crate::params::parse_params(&args.params)?;
    if registry.spec(engine)?.schema.has("accumulate") {
        params.entry("accumulate").or_insert(1.into());
    }
    let mut built = registry.build(engine, &params)?;
    let settings = ReferenceSettings {
        max_bounces: args.bounces,
        seed: args.seed,
        ..offline::reference_settings(w, h, 0, offline::Sampling::Centre, offline::Transport::Full)
    };
    let reference = trace_with_progress(&mut ReferenceRenderer::new(&scene, settings)?, spp);
    let frame = offline::scene_frame(scene.clone(), offline::background(&reference));
    let mut relit = relight_engines::RelitFrame::default();
    built.engine.render(&frame, &mut relit)?;
    let started = Instant::now();
    built.engine.render(&frame, &mut relit)?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    let delta = offline::delta_pixels(&relit.delta);
    let (relative_l2, max_abs) =
        offline::delta_error(&delta, &reference.delta, &reference.virtual_mask);
    let object_l2 =
        offline::object_error(&relit.composite, &reference.l_rho, &reference.virtual_mask);
    let regions = offline::region_errors(&delta, &reference);
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_exr(&out.join("delta.exr"), w, h, &delta)?;
    write_exr(&out.join("delta_reference.exr"), w, h, &reference.delta)?;
    // The truth the object's pixels are judged against, sampled as the engine's are.
    write_exr(&out.join("l_rho_reference.exr"), w, h, &reference.l_rho)?;
    write_virtual_mask(out, w, h, &reference.virtual_mask)?;
    write_png(&out.join("composite.png"), &relit.composite)?;
    let summary = serde_json::json!({
        "scene": scene.name,
        "engine": engine,
        "params": built.params,
        "width": w,
        "height": h,
        "frame_ms": ms,
        "passes": relit.timings.iter().map(|t| serde_json::json!({"pass": t.pass, "ms": t.ms})).collect::<Vec<_>>(),
        "reference_spp": spp,
        "reference_bounces": args.bounces,
        "delta_relative_l2": relative_l2,
        "delta_max_abs": max_abs,
        "object_relative_l2": object_l2,
        "shadow_relative_l2": regions.shadow_relative_l2,
        "bleeding_relative_l2": regions.bleeding_relative_l2,
        "shadow_pixels": regions.shadow_pixels,
        "bleeding_pixels": regions.bleeding_pixels,
    });
    std::fs::write(
        out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    let object = object_l2.map_or("no object pixels".to_owned(), |e| format!("{e:.4}"));
    let region =
        |e: Option<f64>, n: usize| e.map_or("none".to_owned(), |e| format!("{e:.4} ({n} px)"));
    let shadow = region(regions.shadow_relative_l2, regions.shadow_pixels);
    let bleeding = region(regions.bleeding_relative_l2, regions.bleeding_pixels);
    println!(
        "{}: {engine} {w}×{h} in {ms:.1} ms; Δ vs reference ({spp} spp): relative L2 {relative_l2:.4} (shadow {shadow}, bleeding {bleeding}), max abs {max_abs:.4}; object pixels vs L^ρ: relative L2 {object}; wrote {}",
        scene.name,
        out.display()
    );
    Ok(())
}
