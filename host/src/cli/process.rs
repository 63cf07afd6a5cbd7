//! `mlsss process`: run the processing pipeline on a capture up to a stage, printing the report.

use std::path::PathBuf;

use anyhow::Context;
use mlsss::pipeline::{self, CalibrationSource, Pipeline};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The capture folder (`capture.json` + `frames/`).
    capture: PathBuf,
    /// Calibration: a calibration JSON file, or `truth` for a simulated capture's
    /// `truth/calibration.json`. Needed from the geometry stage on.
    #[arg(long)]
    calib: Option<String>,
    /// Last stage to run (its inputs run first; cached stages are reused). Stages: decode, geometry, separate, normals.
    #[arg(long, default_value = "geometry")]
    until: String,
    /// Output folder: one sub-folder per stage, plus report.json.
    #[arg(long)]
    out: PathBuf,
    /// Print the report as one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let calib = match args.calib.as_deref() {
        None => CalibrationSource::None,
        Some("truth") => CalibrationSource::Truth,
        Some(path) => CalibrationSource::File(PathBuf::from(path)),
    };
    let mut pipeline = Pipeline::new(&args.capture, &args.out, &calib)
        .with_context(|| format!("opening {}", args.capture.display()))?;
    pipeline.on_stage = Some(Box::new(|name, cached| {
        eprintln!("{name}{}", if cached { " (cached)" } else { " ..." });
    }));
    let report = pipeline.run_until(&args.until)?;
    if args.json {
        println!("{report}");
    } else {
        eprintln!(
            "report in {}",
            args.out.join(pipeline::REPORT_FILE).display()
        );
        eprintln!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(())
}
