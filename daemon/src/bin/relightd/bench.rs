//! `relightd bench`: every engine × setting × scene timed and scored against the reference
//! (`relight_daemon::bench`), or the `ibl` map convolution alone.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use relight_daemon::bench::{self, BenchSettings};
use relight_engines::offline::{Sampling, Transport};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Scene directories (default: every scene under tests/scenes).
    #[arg(long = "scene")]
    scenes: Vec<PathBuf>,
    #[arg(long, default_value_t = 160)]
    width: u32,
    #[arg(long, default_value_t = 120)]
    height: u32,
    /// Reference samples per pixel to start with.
    #[arg(long, default_value_t = 256)]
    reference_spp: u32,
    /// The most the reference is refined to: samples are added until its noise is under a
    /// third of the best engine's error (each row reports the noise and the samples).
    #[arg(long, default_value_t = 4096)]
    max_reference_spp: u32,
    /// Where references are kept between runs, keyed by the scene's files, the size and the
    /// reference's revision.
    #[arg(long, default_value = "target/bench/references")]
    reference_cache: PathBuf,
    /// Render every reference afresh (and keep none).
    #[arg(long)]
    no_reference_cache: bool,
    /// Timed frames per case (after two warm-up frames); the median is reported.
    #[arg(long, default_value_t = 5)]
    frames: u32,
    /// Still frames every GPU engine accumulates over sub-pixel offsets before its converged
    /// picture is scored against the pixel-area reference (default: each engine's own
    /// `accumulate`; 1: score none).
    #[arg(long)]
    accumulate: Option<u32>,
    /// Also say which term each error comes from: every engine with an `indirect` parameter
    /// is rendered once more with its direct light alone, and each of its two terms is swapped
    /// for the reference's (a direct-light reference, rendered and cached beside the full one);
    /// the error left is the other term's (bench.csv's `direct_term_relative_l2`, ...).
    #[arg(long)]
    terms: bool,
    /// Add the papers' parameter sweeps (DLPV volume × steps and RSM sizes, DVCT volume × step, DIR VPL count and ISM size, IBL map size).
    #[arg(long)]
    sweep: bool,
    /// Only these engines (repeatable).
    #[arg(long = "engine", value_parser = crate::engine_name())]
    engines: Vec<String>,
    /// Exactly these settings instead (repeatable), as bench.csv's `setting` column writes
    /// them: the engine, then `name=value` pairs, e.g. `--case "dir second_bounce=0"`.
    #[arg(long = "case", conflicts_with_all = ["engines", "sweep"])]
    cases: Vec<String>,
    /// Instead of the engine table: time the `ibl` map convolution (diffuse + 8 specular
    /// maps in one pass) at these output sizes, e.g. `--ibl-maps 128,256,512`.
    #[arg(long, value_delimiter = ',')]
    ibl_maps: Vec<u32>,
    /// Also measure the adapter's bandwidth and arithmetic rate with micro-kernels, and print
    /// each pass's achieved fraction of them (roofline.csv, roofline.json).
    #[arg(long)]
    roofline: bool,
    /// How each GPU pass is timed: `timestamps` (timestamp queries) or `wait` (each pass
    /// submitted and waited for, so its time is its own: lavapipe's timestamps give a
    /// submission's later compute passes almost nothing; the frames are slower by what no
    /// longer overlaps).
    #[arg(long, value_enum, default_value_t = PassTimes::Timestamps)]
    pass_times: PassTimes,
    /// Instead of the engine table: the `auto` engine against every fixed engine that fits
    /// each budget (`--budget`), on the scenes (a still camera) and on `--recording` (a moving
    /// one), and `pt`'s error against time beside the CPU reference's (governor.csv,
    /// governor.json, governor.svg, pt_curve.svg).
    #[arg(long)]
    governor: bool,
    /// Frame budgets for `--governor`, milliseconds.
    #[arg(long = "budget", value_delimiter = ',', default_values_t = [10.0, 33.0, 100.0, 1000.0])]
    budgets: Vec<f64>,
    /// Seconds each engine renders a still scene under `--governor` (at most 30 frames a
    /// second): the picture is judged this long after the scene appears.
    #[arg(long, default_value_t = 4.0)]
    governor_seconds: f64,
    /// A simulated recording with ground truth for `--governor`, with the scene it was made
    /// from (`--recording-scene`); the bundled one by default. `none`: scenes only.
    #[arg(long, default_value = "tests/fixtures/demo.mcap")]
    recording: String,
    #[arg(long, default_value = "tests/scenes/desk_box")]
    recording_scene: PathBuf,
    /// Samples per pixel of the recording's truth renders.
    #[arg(long, default_value_t = 16)]
    recording_reference_spp: u32,
    /// Seconds of `pt`'s and the CPU reference's error-against-time curves per scene (0: none).
    #[arg(long, default_value_t = 5.0)]
    curve_seconds: f64,
    /// Where bench.csv, bench.json and bench.svg (or ibl_maps.csv) are written.
    #[arg(long, default_value = "target/bench")]
    out: PathBuf,
}

pub fn run(mut args: Args) -> Result<()> {
    if !args.ibl_maps.is_empty() {
        println!("size     input texels  maps  median ms");
        let mut csv = String::from("size,input_texels,maps,median_ms\n");
        for row in bench::ibl_map_timings(&args.ibl_maps, 8, args.frames)? {
            println!(
                "{:>4}²  {:>13}  {:>4}  {:>9.1}",
                row.size,
                row.input_texels,
                row.levels + 1,
                row.median_ms
            );
            csv += &format!(
                "{},{},{},{}\n",
                row.size,
                row.input_texels,
                row.levels + 1,
                row.median_ms
            );
        }
        std::fs::create_dir_all(&args.out)
            .with_context(|| format!("creating {}", args.out.display()))?;
        let path = args.out.join("ibl_maps.csv");
        std::fs::write(&path, csv).with_context(|| format!("writing {}", path.display()))?;
        println!("wrote {}", path.display());
        return Ok(());
    }
    let scenes = if args.scenes.is_empty() {
        let mut found: Vec<PathBuf> = std::fs::read_dir("tests/scenes")
            .context("no --scene given and no tests/scenes here")?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join("scene.toml").exists())
            .collect();
        found.sort();
        found
    } else {
        std::mem::take(&mut args.scenes)
    };
    if args.governor {
        return governor(args, scenes);
    }
    let all_cases = bench::default_cases(args.sweep);
    let mut benched: Vec<&str> = all_cases.iter().map(|c| c.engine.as_str()).collect();
    benched.dedup();
    let registry = relight_engines::EngineRegistry::new();
    let chosen = args
        .cases
        .iter()
        .map(|setting| {
            bench::BenchCase::parse(setting, &registry)
                .with_context(|| format!("--case {setting:?}"))
        })
        .collect::<Result<Vec<_>>>()?;
    if let Some(unknown) = args
        .engines
        .iter()
        .chain(chosen.iter().map(|c| &c.engine))
        .find(|e| !benched.contains(&e.as_str()))
    {
        bail!(
            "{unknown}: not an engine the bench runs; it runs {}",
            benched.join(", ")
        );
    }
    let cases = if chosen.is_empty() {
        all_cases
            .into_iter()
            .filter(|c| args.engines.is_empty() || args.engines.contains(&c.engine))
            .collect()
    } else {
        chosen
    };
    let settings = bench_settings(&args, scenes, cases);
    let context = relight_engines::gpu::GpuContext::new();
    let adapter = context
        .as_ref()
        .map(|c| format!("{} ({:?})", c.info.name, c.info.backend))
        .unwrap_or_else(|e| format!("no GPU: {e}"));
    // bench.json and roofline.json say how their pass times were taken.
    let adapter = match args.pass_times {
        PassTimes::Timestamps => adapter,
        PassTimes::Wait => format!("{adapter}; each pass timed by waiting for it"),
    };
    eprintln!("bench on {adapter}");
    let rates = if args.roofline {
        let context = context.map_err(|e| anyhow::anyhow!("--roofline needs a GPU: {e}"))?;
        let rates = relight_engines::roofline::measure(&context)?;
        eprintln!(
            "roofline: {:.2} GB/s, {:.2} Gop/s",
            rates.bytes_per_s / 1e9,
            rates.ops_per_s / 1e9
        );
        Some(rates)
    } else {
        None
    };
    // A bar on a terminal; on a pipe or in a log, one line per reference and per row.
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} cases  {elapsed}  {msg}")
            .expect("a valid template"),
    );
    let say = |line: String| {
        if bar.is_hidden() {
            eprintln!("{line}");
        } else {
            bar.println(line);
        }
    };
    let rows = bench::run(&settings, |event| match event {
        bench::BenchProgress::Reference {
            scene,
            sampling,
            transport,
            spp,
            cached,
        } => {
            let which = match (sampling, transport) {
                (Sampling::Centre, Transport::Full) => "reference",
                (Sampling::Area, Transport::Full) => "pixel-area reference",
                (Sampling::Centre, Transport::Direct) => "direct-light reference",
                (Sampling::Area, Transport::Direct) => "pixel-area direct-light reference",
            };
            bar.set_message(format!("{scene}: {which} at {spp} spp"));
            say(if cached {
                format!("{scene}: the cached {which} ({spp} spp)")
            } else {
                format!("{scene}: rendering the {which} to {spp} spp")
            });
        }
        bench::BenchProgress::Case {
            scene,
            setting,
            done,
            total,
        } => {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
            bar.set_message(format!("{scene}: {setting}"));
        }
        bench::BenchProgress::Row(row) => say(format!(
            "{:<14} {:<52} {:>9.2} ms  rel L2 {:.4}",
            row.scene, row.setting, row.median_ms, row.relative_l2
        )),
    })?;
    bar.finish_and_clear();
    print!("{}", bench::table(&rows));
    if args.terms {
        print!("{}", bench::terms_table(&rows));
    }
    bench::write_outputs(&rows, &args.out, &adapter)?;
    println!("wrote {}/bench.{{csv,json,svg}}", args.out.display());
    if let Some(rates) = rates {
        let roofline = bench::roofline_rows(&rows, &rates);
        print!("{}", bench::roofline_table(&rates, &roofline));
        bench::write_roofline(&rates, &roofline, &args.out, &adapter)?;
        println!("wrote {}/roofline.{{csv,json}}", args.out.display());
    }
    Ok(())
}

/// The scenes, size, references and frames the arguments ask for.
fn bench_settings(
    args: &Args,
    scenes: Vec<PathBuf>,
    cases: Vec<bench::BenchCase>,
) -> BenchSettings {
    BenchSettings {
        scenes,
        width: args.width,
        height: args.height,
        reference_spp: args.reference_spp,
        max_reference_spp: args.max_reference_spp,
        reference_cache: (!args.no_reference_cache).then(|| args.reference_cache.clone()),
        frames: args.frames,
        accumulate: args.accumulate,
        terms: args.terms,
        wait_per_pass: args.pass_times == PassTimes::Wait,
        cases,
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum PassTimes {
    Timestamps,
    Wait,
}

fn governor(args: Args, scenes: Vec<PathBuf>) -> Result<()> {
    use relight_daemon::governor_bench::{self, GovernorProgress, GovernorSettings};
    let settings = GovernorSettings {
        bench: bench_settings(&args, scenes, Vec::new()),
        budgets_ms: args.budgets,
        seconds: args.governor_seconds,
        recording: (args.recording != "none")
            .then(|| (PathBuf::from(&args.recording), args.recording_scene)),
        recording_reference_spp: args.recording_reference_spp,
        curve_seconds: args.curve_seconds,
    };
    let adapter = relight_engines::gpu::GpuContext::new()
        .map(|c| format!("{} ({:?})", c.info.name, c.info.backend))
        .unwrap_or_else(|e| format!("no GPU: {e}"));
    eprintln!("governor bench on {adapter}");
    let report = governor_bench::run(&settings, |event| match event {
        GovernorProgress::Reference(bench::BenchProgress::Reference {
            scene, spp, cached, ..
        }) => eprintln!(
            "{scene}: {} the pixel-area reference ({spp} spp)",
            if cached { "cached" } else { "rendering" }
        ),
        GovernorProgress::Reference(_) => {}
        GovernorProgress::Run { scene, engine } => eprintln!("{scene}: {engine}"),
    })?;
    print!("{}", governor_bench::table(&report));
    governor_bench::write_outputs(&report, &args.out, &adapter)?;
    println!(
        "wrote {}/governor.{{csv,json,svg}}{}",
        args.out.display(),
        if report.curve.is_empty() {
            ""
        } else {
            " and pt_curve.svg"
        }
    );
    Ok(())
}
