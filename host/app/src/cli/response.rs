//! `mlsss response`: projector response curves (gamma, black level) from calibration captures,
//! written into the calibration JSON (`projectors[k].response`).

use std::path::PathBuf;

use anyhow::{Context, bail};
use mlsss::calibration::Calibration;
use mlsss::capture::{Capture, Pattern};
use mlsss::photometry::response::{LevelFrames, estimate_responses};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Calibration capture folders (one per board pose, each with white, black and grey levels
    /// per projector, as `mlsss simulate --calibration` or the rig write them).
    #[arg(required = true)]
    poses: Vec<PathBuf>,
    /// Calibration JSON to update (its projectors get a `response`); without it only the report
    /// is printed.
    #[arg(long)]
    calib: Option<PathBuf>,
    /// Where to write the updated calibration (default: overwrite --calib).
    #[arg(long, requires = "calib")]
    out: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

/// Level in [0, 1] of the full-field patterns the response uses.
fn level(pattern: &Pattern) -> Option<f64> {
    match *pattern {
        Pattern::White => Some(1.0),
        Pattern::Black => Some(0.0),
        Pattern::Grey { level_milli } => Some(level_milli as f64 / 1000.0),
        _ => None,
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut poses = Vec::new();
    for dir in &args.poses {
        let capture = Capture::open(dir).with_context(|| format!("opening {}", dir.display()))?;
        let projectors = capture.manifest.booth.projectors.len();
        let mut per_projector = Vec::new();
        for k in 0..projectors {
            let mut frames = LevelFrames::default();
            for spec in capture.manifest.plan.for_projector(k as u8) {
                if let Some(l) = level(&spec.pattern) {
                    frames.frames.push((l, capture.read(spec)?));
                }
            }
            per_projector.push(frames);
        }
        poses.push(per_projector);
    }
    let fits = estimate_responses(&poses)?;
    let mut report = serde_json::json!({ "projectors": fits });
    if let Some(path) = &args.calib {
        let mut calib = Calibration::load(path)?;
        if calib.projectors.len() < fits.len() {
            bail!(
                "{} has {} projectors but the captures have {}",
                path.display(),
                calib.projectors.len(),
                fits.len()
            );
        }
        for (p, fit) in calib.projectors.iter_mut().zip(&fits) {
            p.response = Some(fit.response());
        }
        let out = args.out.as_ref().unwrap_or(path);
        calib.save(out)?;
        report["written"] = serde_json::json!(out);
    }
    if args.json {
        println!("{report}");
    } else {
        eprintln!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(())
}
