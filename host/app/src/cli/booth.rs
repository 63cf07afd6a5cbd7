//! `mlsss booth`: parse and validate a booth description, summarise its frame plan.

use std::path::PathBuf;

use anyhow::Context;
use mlsss::booth::Booth;
use mlsss::capture::FramePlan;

#[derive(Debug, clap::Args)]
pub struct Args {
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

pub fn run(args: Args) -> anyhow::Result<()> {
    let booth = match &args.file {
        Some(path) => {
            Booth::from_file(path).with_context(|| format!("loading booth {}", path.display()))?
        }
        None => Booth::builtin(args.quick),
    };
    let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
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
