//! `mlsss`: the command-line program. A thin layer over the `mlsss` library: argument parsing,
//! progress and error reporting; all work happens in the library.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};

/// Measure and render the multi-layered subsurface scattering of skin (MLSSS) from a booth of
/// four projectors and one camera.
#[derive(Debug, Parser)]
#[command(name = "mlsss", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Inspect a booth description: parse and validate it, print the frame plan summary.
    Booth(BoothArgs),
}

#[derive(Debug, clap::Args)]
struct BoothArgs {
    /// Booth file (default: the built-in hardware/booth.toml).
    #[arg(long)]
    file: Option<PathBuf>,
    /// Use the built-in --quick booth.
    #[arg(long, conflicts_with = "file")]
    quick: bool,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Booth(args) => run_booth(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn run_booth(args: BoothArgs) -> anyhow::Result<()> {
    let booth = match &args.file {
        Some(path) => mlsss::booth::Booth::from_file(path)
            .with_context(|| format!("loading booth {}", path.display()))?,
        None => mlsss::booth::Booth::builtin(args.quick),
    };
    let plan = mlsss::capture::FramePlan::scan(&booth.patterns, booth.projectors.len());
    let seconds = plan.len() as f64 / booth.timing.fps;
    if args.json {
        let value = serde_json::json!({
            "name": booth.name,
            "camera": [booth.camera.width, booth.camera.height],
            "projectors": booth.projectors.len(),
            "frames": plan.len(),
            "capture_seconds": seconds,
        });
        println!("{value}");
    } else {
        println!(
            "booth '{}': camera {}x{}, {} projectors, {} frames, {:.1} s at {} fps",
            booth.name,
            booth.camera.width,
            booth.camera.height,
            booth.projectors.len(),
            plan.len(),
            seconds,
            booth.timing.fps
        );
    }
    Ok(())
}
