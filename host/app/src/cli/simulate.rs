//! `mlsss simulate`: render a capture (or chessboard calibration captures) in the virtual booth,
//! with ground truth under `truth/` (unless `--no-truth`) and a contact sheet PNG.

use std::path::PathBuf;

use anyhow::Context;

use super::monte_carlo_args::MonteCarloArgs;
use super::stage_bar::Bar;
use mlsss::booth::Booth;
use mlsss::virtual_booth::subsurface_transport::MIN_INNER_BAND_PIXELS;
use mlsss::virtual_booth::{
    SimulationOptions, SkinPreset, SubjectKind, scaled_booth, simulate_calibration, simulate_scan,
};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Use the built-in --quick booth (small images, 8-bit Gray code).
    #[arg(long, conflicts_with = "booth")]
    quick: bool,
    /// Shrink the booth further by this factor (images and focal lengths), for fast tests.
    #[arg(long, value_name = "FACTOR", default_value_t = 1)]
    scale_down: u32,
    /// Booth description (default: the built-in hardware/booth.toml).
    #[arg(long, value_name = "FILE")]
    booth: Option<PathBuf>,
    /// What stands in the booth.
    #[arg(long, value_enum)]
    subject: SubjectKind,
    /// Skin type (optical properties from the literature).
    #[arg(long, value_enum, default_value_t = SkinPreset::LIGHT)]
    skin: SkinPreset,
    /// Seed of everything random (material maps, noise, board poses).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Render chessboard calibration captures (one capture folder per pose under --out).
    #[arg(long, requires = "poses")]
    calibration: bool,
    /// Number of chessboard poses for --calibration.
    #[arg(long, value_name = "K")]
    poses: Option<usize>,
    /// Uniform skin: no freckles, vessels or stubble.
    #[arg(long)]
    no_maps: bool,
    /// Dark projectors emit nothing (default: they emit their black level, as real ones do).
    #[arg(long)]
    no_stray_black: bool,
    /// Take every frame at the booth's nominal exposure (no metering step before the scan).
    #[arg(long)]
    fixed_exposure: bool,
    /// Leave out the `truth/` folder, as a real booth's capture comes (processing it then needs
    /// a calibration file, `--calib FILE`, and reports no errors against the truth).
    #[arg(long)]
    no_truth: bool,
    /// Camera sub-samples per pixel along each axis.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=4))]
    supersampling: u32,
    /// Innermost band of the subsurface transport, in pixels (3 to 16): wider is more exact and
    /// slower, its cost growing with the square (the quick head scan: 3 px 8.6 CPU-s, 4 px 11.4,
    /// 8 px 32). Default: 3 on small booths, 4 at full size.
    #[arg(long, value_name = "PX", value_parser = inner_band_px)]
    inner_band_px: Option<f64>,
    #[command(flatten)]
    monte_carlo: MonteCarloArgs,
    /// Output capture folder (must not exist).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Print one JSON object (the report) on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut booth = match &args.booth {
        Some(path) => {
            Booth::from_file(path).with_context(|| format!("loading booth {}", path.display()))?
        }
        None => Booth::builtin(args.quick),
    };
    if args.scale_down > 1 {
        booth = scaled_booth(&booth, args.scale_down);
    }
    if args.calibration && args.subject != SubjectKind::Chessboard {
        anyhow::bail!("--calibration needs --subject chessboard");
    }
    let mut opts = SimulationOptions::for_booth(&booth, args.subject, args.skin, args.seed);
    opts.material_maps = !args.no_maps;
    opts.stray_black = !args.no_stray_black;
    opts.metering = !args.fixed_exposure;
    opts.truth = !args.no_truth;
    opts.supersampling = args.supersampling;
    if let Some(px) = args.inner_band_px {
        opts.inner_band_px = px;
    }
    args.monte_carlo.apply(&mut opts);
    let progress = Bar::on_stderr()?;
    let report = if args.calibration {
        let poses = args.poses.unwrap_or(1);
        anyhow::ensure!(poses > 0, "--poses must be at least 1");
        simulate_calibration(&booth, &opts, poses, &args.out, &progress)
    } else {
        simulate_scan(&booth, &opts, &args.out, &progress)
    }
    .with_context(|| format!("simulating into {}", args.out.display()))?;
    progress.finish_and_clear();
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        eprintln!(
            "wrote {} frames in {:.1} s to {} (Monte Carlo: {} cached, {} computed in {:.1} s; cache {})",
            report.frames,
            report.seconds,
            args.out.display(),
            report.cache.hits,
            report.cache.misses,
            report.cache.mc_seconds,
            opts.cache.dir().display(),
        );
    }
    Ok(())
}

/// Widest `--inner-band-px`: the quick scan already costs three times as much at 8 px.
const MAX_INNER_BAND_PX: f64 = 16.0;

/// Parses `--inner-band-px`: pixels from the narrowest band the kernel allows
/// ([`MIN_INNER_BAND_PIXELS`]) to [`MAX_INNER_BAND_PX`].
fn inner_band_px(s: &str) -> Result<f64, String> {
    super::number_arg::finite_in(s, MIN_INNER_BAND_PIXELS..=MAX_INNER_BAND_PX)
}
