//! `mlsss bench`: runtime against held-out error over the main quality knobs (components, EM
//! tolerance and iterations, profile sampling, kernel truncation, resolution), as a CSV table and
//! a Pareto-front plot.

use std::path::{Path, PathBuf};

use anyhow::Context;
use mlsss::booth::Booth;
use mlsss::pipeline::CalibrationSource;
use mlsss::quality_sweep::{SweepInputs, plan, run_sweep, summary, write_outputs};
use mlsss::virtual_booth::{
    NoProgress, SimulationOptions, SkinPreset, SubjectKind, scaled_booth, simulate_scan,
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

pub fn run(args: Args) -> anyhow::Result<()> {
    anyhow::ensure!(args.scale_down >= 1, "--scale-down must be at least 1");
    ensure_dir(&args.out)?;
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
