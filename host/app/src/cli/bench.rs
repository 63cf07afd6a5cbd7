//! `mlsss bench`: runtime against held-out error over the main quality knobs (components, EM
//! tolerance and iterations, profile sampling, kernel truncation, resolution), as a CSV table and
//! a Pareto-front plot.

use std::path::{Path, PathBuf};

use anyhow::Context;
use mlsss::booth::Booth;
use mlsss::demo::{CalibrationMode, DemoOptions, DemoProgress, run_demo};
use mlsss::evaluate::separation_race;
use mlsss::evaluate::skin_types::{self, row_from_demo};
use mlsss::evaluate::stripe_sweep;
use mlsss::pipeline::separate_stage::SeparateParams;
use mlsss::pipeline::{CalibrationSource, Pipeline};
use mlsss::quality_sweep::{SweepInputs, plan, run_sweep, summary, write_outputs};
use mlsss::virtual_booth::{
    NoProgress, Progress, SimulationOptions, SkinPreset, SubjectKind, scaled_booth, simulate_scan,
};

use super::monte_carlo_args::MonteCarloArgs;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The small --quick booth and a short sweep (the full-size booth and a longer sweep
    /// otherwise).
    #[arg(long)]
    quick: bool,
    /// Shrink the reference booth by this factor; the resolution knob adds the booth shrunk
    /// twice as much.
    #[arg(long, value_name = "FACTOR", default_value_t = 1)]
    scale_down: u32,
    /// Only the reference configuration and one value per knob at the reference resolution
    /// (a smoke run, e.g. for tests).
    #[arg(long)]
    minimal: bool,
    /// Projector held out of the fit and used for the error.
    #[arg(long, default_value_t = 3)]
    holdout: usize,
    /// Seed of the simulated head.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Instead of the quality sweep: the per-skin-type table. One demo per Fitzpatrick type I-VI
    /// (simulator's calibration, metering on) under OUT/skin-types/TYPE, reduced to decode
    /// coverage, normals, subsurface errors and the paper's two claims; writes
    /// OUT/skin_types.csv and prints `skin_types` in the JSON.
    #[arg(long)]
    skin_types: bool,
    /// Instead of the quality sweep: separation error against the ratio of the stripe period to
    /// the subsurface kernel's width. One capture per skin type (all six; I and VI with
    /// --minimal) and stripe width (--stripes) under OUT/stripe-sweep, separated by the
    /// kernel-aware method and by Nayar et al.'s against the truth; writes OUT/stripe_sweep.csv
    /// and OUT/stripe_sweep.html (both plots and the table).
    #[arg(long, conflicts_with = "skin_types")]
    stripe_sweep: bool,
    /// Instead of the quality sweep: race the separate and normals stages' variants on CAPTURE
    /// (`paper`: Nayar and Lambertian photometric stereo, the baseline; `dichromatic`;
    /// `lobe_with_leak`; `lobe`, the default), alternated over --rounds, each in its own folder
    /// under OUT/separation-race; prints the median CPU and wall seconds of the two stages, their
    /// ratios to the baseline and the errors against the truth, writes
    /// OUT/separation_race.csv. A simulated capture (`--calib truth`) or `--calib FILE`.
    #[arg(long, value_name = "CAPTURE", conflicts_with_all = ["skin_types", "stripe_sweep"])]
    separation_race: Option<PathBuf>,
    /// Rounds of --separation-race.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100))]
    rounds: u32,
    /// Calibration of --separation-race: `truth` (the simulator's) or a calibration file.
    #[arg(long, default_value = "truth")]
    calib: String,
    /// Skin types of --stripe-sweep (default: all six; I and VI with --minimal).
    #[arg(long, value_enum, value_delimiter = ',')]
    skins: Vec<SkinPreset>,
    /// Stripe widths of --stripe-sweep, projector px (the booth's own is 3).
    #[arg(long, value_delimiter = ',', default_value = "2,3,4,6,8", value_parser = clap::value_parser!(u32).range(1..=64))]
    stripes: Vec<u32>,
    #[command(flatten)]
    monte_carlo: MonteCarloArgs,
    /// Output folder: captures (simulated once, reused on later runs), pipeline outputs,
    /// bench.csv, pareto.png.
    #[arg(long, default_value = "out/bench")]
    out: PathBuf,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

/// Simulates (or reuses) the head capture of the booth shrunk by `factor`.
fn capture_for(args: &Args, factor: u32) -> anyhow::Result<(PathBuf, PathBuf)> {
    let dir = args.out.join(format!("capture-div{factor}"));
    let processed = args.out.join(format!("processed-div{factor}"));
    if dir.join("capture.json").is_file() {
        eprintln!("reusing {}", dir.display());
        return Ok((dir, processed));
    }
    let mut booth = Booth::builtin(args.quick);
    if factor > 1 {
        booth = scaled_booth(&booth, factor);
    }
    let mut opts =
        SimulationOptions::for_booth(&booth, SubjectKind::Head, SkinPreset::LIGHT, args.seed);
    args.monte_carlo.apply(&mut opts);
    eprintln!(
        "simulating a {}x{} capture ...",
        booth.camera.width, booth.camera.height
    );
    simulate_scan(&booth, &opts, &dir, &NoProgress)
        .with_context(|| format!("simulating {}", dir.display()))?;
    Ok((dir, processed))
}

fn ensure_dir(dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))
}

/// The per-skin-type table: a demo of each type, then the table (`evaluate::skin_types`).
fn run_skin_types(args: &Args) -> anyhow::Result<()> {
    let mut rows = Vec::new();
    for skin in SkinPreset::ALL {
        let dir = args.out.join("skin-types").join(skin.label());
        let mut opts = DemoOptions::new(args.quick, args.scale_down, &dir);
        opts.skin = skin;
        opts.seed = args.seed;
        opts.holdout = args.holdout;
        opts.calibration = CalibrationMode::Truth;
        opts.photons = args.monte_carlo.photons;
        opts.cache = args.monte_carlo.cache.clone();
        eprintln!("skin type {} ...", skin.label());
        let outcome = run_demo(&opts, &QuietDemo)
            .with_context(|| format!("demo of skin type {}", skin.label()))?;
        rows.push(row_from_demo(skin.label(), skin.melanin(), &outcome.report));
    }
    let table = skin_types::table(rows);
    let csv = args.out.join("skin_types.csv");
    mlsss_core::atomic_file::write_bytes_atomically(&csv, skin_types::to_csv(&table))
        .with_context(|| format!("writing {}", csv.display()))?;
    let html = args.out.join("skin_types.html");
    skin_types::to_html(&table)
        .save(&html)
        .with_context(|| format!("writing {}", html.display()))?;
    if args.json {
        println!(
            "{}",
            serde_json::json!({ "skin_types": table, "csv": csv, "html": html })
        );
    } else {
        eprint!("{}", skin_types::to_csv(&table));
        eprintln!("wrote {}", csv.display());
    }
    Ok(())
}

/// The separate and normals stages' variants raced on `capture` (`evaluate::separation_race`).
fn run_separation_race(args: &Args, capture: &Path) -> anyhow::Result<()> {
    let calibration = match args.calib.as_str() {
        "truth" => CalibrationSource::Truth,
        file => CalibrationSource::File(PathBuf::from(file)),
    };
    let out = args.out.join("separation-race");
    let variants = separation_race::variants();
    let runs = separation_race::race(
        capture,
        &out,
        &calibration,
        &variants,
        args.rounds as usize,
        &|run| {
            let cpu = run.cpu_s.map_or("-".into(), |c| format!("{c:.2}"));
            eprintln!(
                "round {} {:<15} separate+normals {cpu} CPU-s, {:.2} s wall",
                run.round, run.variant, run.wall_s
            );
        },
    )?;
    let summary = separation_race::summarise(&runs);
    let csv_text = separation_race::to_csv(&summary);
    let csv = args.out.join("separation_race.csv");
    mlsss_core::atomic_file::write_bytes_atomically(&csv, &csv_text)
        .with_context(|| format!("writing {}", csv.display()))?;
    if args.json {
        println!(
            "{}",
            serde_json::json!({ "separation_race": summary, "runs": runs, "csv": csv })
        );
    } else {
        eprint!("{csv_text}");
        eprintln!("wrote {}", csv.display());
    }
    Ok(())
}

/// The separation-versus-kernel-width sweep (`evaluate::stripe_sweep`): a capture per skin type
/// and stripe width, separated against the truth.
fn run_stripe_sweep(args: &Args) -> anyhow::Result<()> {
    let skins: Vec<SkinPreset> = if !args.skins.is_empty() {
        args.skins.clone()
    } else if args.minimal {
        vec![SkinPreset::TypeI, SkinPreset::TypeVI]
    } else {
        SkinPreset::ALL.to_vec()
    };
    let mut base = Booth::builtin(args.quick);
    if args.scale_down > 1 {
        base = scaled_booth(&base, args.scale_down);
    }
    let total = skins.len() * args.stripes.len();
    let mut rows = Vec::with_capacity(total);
    for skin in &skins {
        // The kernel depends on the skin alone (the Monte Carlo settings on the camera, not on
        // the stripes): read once per type, from the cache the simulations share.
        let mut kernel_opts =
            SimulationOptions::for_booth(&base, SubjectKind::Head, *skin, args.seed);
        args.monte_carlo.apply(&mut kernel_opts);
        let (responses, _) = kernel_opts
            .cache
            .response_set(&skin.materials()[..1], &kernel_opts.mc, &|_| {})
            .context("reading the Monte Carlo responses")?;
        let grid = responses
            .grids
            .first()
            .and_then(|g| g.first())
            .context("no Monte Carlo response at normal incidence")?;
        let width = stripe_sweep::line_spread_width_mm(grid);
        for &stripe in &args.stripes {
            eprintln!(
                "[{}/{total}] skin type {}, stripes {stripe} px ...",
                rows.len() + 1,
                skin.label()
            );
            let mut booth = base.clone();
            booth.patterns.hf_stripe_px = stripe;
            mlsss::booth::validate_patterns(&booth.patterns)
                .with_context(|| format!("--stripes {stripe}"))?;
            let name = format!("{}-stripe{stripe}", skin.label());
            let dir = args.out.join("stripe-sweep").join(&name);
            let mut opts =
                SimulationOptions::for_booth(&booth, SubjectKind::Head, *skin, args.seed);
            args.monte_carlo.apply(&mut opts);
            if !dir.join("capture.json").is_file() {
                simulate_scan(&booth, &opts, &dir, &NoProgress)
                    .with_context(|| format!("simulating {}", dir.display()))?;
            }
            let processed = args.out.join("stripe-sweep").join(format!("{name}-out"));
            let mut pipeline = Pipeline::new(&dir, &processed, &CalibrationSource::Truth)?;
            // The leak's figures need the slit sweep, which the lobe alone does not read.
            let separate = SeparateParams {
                leak_with_lobe: true,
                ..SeparateParams::default()
            };
            pipeline.set_params("separate", serde_json::to_value(&separate)?);
            let report = pipeline
                .run_until("separate")
                .with_context(|| format!("separating {}", dir.display()))?;
            let separate = report
                .separate
                .context("the separate stage gave no report")?;
            let period = stripe_sweep::stripe_period_mm(&booth, stripe);
            rows.push(
                stripe_sweep::row(skin.label(), stripe, period, width, &separate)
                    .context("the separation gave no truth comparison or no kernel leak")?,
            );
        }
    }
    let csv = args.out.join("stripe_sweep.csv");
    mlsss_core::atomic_file::write_bytes_atomically(&csv, stripe_sweep::to_csv(&rows))
        .with_context(|| format!("writing {}", csv.display()))?;
    let html = args.out.join("stripe_sweep.html");
    stripe_sweep::to_html(&rows)?
        .save(&html)
        .with_context(|| format!("writing {}", html.display()))?;
    if args.json {
        println!(
            "{}",
            serde_json::json!({ "stripe_sweep": rows, "csv": csv, "html": html })
        );
    } else {
        eprint!("{}", stripe_sweep::to_csv(&rows));
        eprintln!("wrote {} and {}", csv.display(), html.display());
    }
    Ok(())
}

/// Demo progress that prints nothing (the table run reports per type).
struct QuietDemo;

impl DemoProgress for QuietDemo {
    fn step(&self, _: &str) {}
}

impl Progress for QuietDemo {
    fn stage(&self, _: &str, _: u64) {}
    fn advance(&self, _: u64) {}
}

pub fn run(args: Args) -> anyhow::Result<()> {
    anyhow::ensure!(args.scale_down >= 1, "--scale-down must be at least 1");
    ensure_dir(&args.out)?;
    if args.skin_types {
        return run_skin_types(&args);
    }
    if args.stripe_sweep {
        return run_stripe_sweep(&args);
    }
    if let Some(capture) = &args.separation_race {
        return run_separation_race(&args, capture);
    }
    let factors = if args.minimal {
        vec![args.scale_down]
    } else {
        vec![args.scale_down, 2 * args.scale_down]
    };
    let captures = factors
        .iter()
        .map(|&f| capture_for(&args, f))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let mut configs = plan(args.quick, captures.len());
    if args.minimal {
        // One value per knob: the first of each.
        let mut seen = Vec::new();
        configs.retain(|c| {
            let new = !seen.contains(&c.knob);
            seen.push(c.knob.clone());
            new
        });
    }
    let inputs = SweepInputs {
        captures,
        calibration: CalibrationSource::Truth,
        holdout: args.holdout,
    };
    let total = configs.len();
    let rows = run_sweep(&inputs, &configs, &|i, c| {
        eprintln!("[{}/{total}] {} = {}", i + 1, c.knob, c.value);
    })?;
    let (csv, png) = write_outputs(&args.out, &rows)?;
    let report = summary(&rows, &csv, &png);
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        eprint!("{}", mlsss::quality_sweep::to_csv(&rows));
        eprintln!("wrote {} and {}", csv.display(), png.display());
    }
    Ok(())
}
