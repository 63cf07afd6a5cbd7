//! `mlsss demo`: simulate, calibrate, process with a projector held out, relight it and evaluate
//! against the truth (the project's main command).

use std::path::PathBuf;

use anyhow::Context;

use super::monte_carlo_args::MonteCarloArgs;
use super::stage_bar::Bar;
use mlsss::demo::{CalibrationMode, DemoOptions, DemoProgress, run_demo};
use mlsss::virtual_booth::{Progress, SkinPreset, SubjectKind};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum CalibChoice {
    /// Calibrate from simulated chessboard poses, as with a real booth.
    Estimated,
    /// Use the simulator's exact calibration (isolates the rest from calibration error).
    Truth,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Use the small built-in --quick booth (fast; the full-size booth otherwise).
    #[arg(long)]
    quick: bool,
    /// Shrink the booth further by this factor (images and focal lengths): tiny scenes for tests.
    #[arg(long, value_name = "FACTOR", default_value_t = 1)]
    scale_down: u32,
    /// What stands in the booth.
    #[arg(long, value_enum, default_value_t = SubjectKind::Head)]
    subject: SubjectKind,
    /// Skin type (optical properties from the literature).
    #[arg(long, value_enum, default_value_t = SkinPreset::LIGHT)]
    skin: SkinPreset,
    /// Seed of everything random (material maps, noise, board poses).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Take every frame at the booth's nominal exposure (no metering step before the scan; how
    /// the demo ran before metering).
    #[arg(long)]
    fixed_exposure: bool,
    /// Projector held out of the fit, relit from the model and compared with its frames.
    #[arg(long, default_value_t = 3)]
    holdout: usize,
    /// Where the calibration comes from.
    #[arg(long, value_enum, default_value_t = CalibChoice::Estimated)]
    calib: CalibChoice,
    /// Chessboard poses simulated for an estimated calibration.
    #[arg(long, default_value_t = 5)]
    poses: usize,
    /// Fit: Gaussian components per fit at the start (the paper: 20; BIC prunes).
    #[arg(long, default_value_t = mlsss::demo::quick_fit_params().components)]
    components: usize,
    /// Fit: one EM fit per BLOCK x BLOCK pixel tile, each pixel keeping its own amplitude
    /// (1 = every pixel, slow).
    #[arg(long, default_value_t = mlsss::demo::quick_fit_params().block)]
    block: usize,
    /// Fit: EM iteration cap per pixel.
    #[arg(long, default_value_t = 200)]
    max_iterations: usize,
    #[command(flatten)]
    monte_carlo: MonteCarloArgs,
    /// Output folder (created; a previous demo's outputs in it are replaced).
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Print the report as one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

impl DemoProgress for Bar {
    fn step(&self, name: &str) {
        self.0.println(format!("== {name}"));
        self.stage(name, 1);
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    anyhow::ensure!(args.scale_down >= 1, "--scale-down must be at least 1");
    let mut opts = DemoOptions::new(args.quick, args.scale_down, &args.out);
    opts.subject = args.subject;
    anyhow::ensure!(
        opts.subject != SubjectKind::Chessboard,
        "--subject chessboard is a calibration target, not a skin subject"
    );
    opts.skin = args.skin;
    opts.seed = args.seed;
    opts.metering = !args.fixed_exposure;
    opts.holdout = args.holdout;
    opts.calibration = match args.calib {
        CalibChoice::Truth => CalibrationMode::Truth,
        CalibChoice::Estimated => CalibrationMode::Estimated { poses: args.poses },
    };
    opts.fit.components = args.components;
    opts.fit.block = args.block;
    opts.fit.max_iterations = args.max_iterations;
    opts.photons = args.monte_carlo.photons;
    opts.cache = args.monte_carlo.cache.clone();
    let progress = Bar::on_stderr()?;
    let outcome =
        run_demo(&opts, &progress).with_context(|| format!("demo into {}", args.out.display()))?;
    progress.finish_and_clear();
    if args.json {
        println!("{}", serde_json::to_string(&outcome.report)?);
    } else {
        eprintln!("{}", serde_json::to_string_pretty(&outcome.report)?);
        eprintln!(
            "report: {}",
            args.out.join(mlsss::demo::REPORT_FILE).display()
        );
    }
    Ok(())
}
