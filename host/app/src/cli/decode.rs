//! `mlsss decode`: Gray-code decoding of a capture folder (every projector) or of an OpenCV-ordered
//! sequence (one projector), to coordinate maps (EXR), confidence and false-colour previews.

use std::path::PathBuf;
use std::time::Instant;

use super::size_arg::parse_size;
use anyhow::{Context, bail};
use mlsss::geometry::code_frames;
use mlsss::geometry::gray_code::{DecodeParams, decode_timed};
use mlsss::pipeline::{self, CalibrationSource, Pipeline};
use mlsss::resources::cpu_seconds;
use serde_json::json;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Layout {
    /// Our capture folder (`capture.json` + `frames/`); every projector is decoded.
    Capture,
    /// A folder of PNGs in OpenCV's order: per bit (coarse to fine) pattern then inverse, column
    /// bits then row bits, then white and black. One projector; needs --projector.
    Opencv,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The capture folder (or, with --layout opencv, the folder of PNG frames).
    capture: PathBuf,
    /// Output folder (capture layout: artefacts go to OUT/decode/, cached by content).
    #[arg(long)]
    out: PathBuf,
    /// How the frames are organised.
    #[arg(long, value_enum, default_value_t = Layout::Capture)]
    layout: Layout,
    /// Projector resolution WIDTHxHEIGHT (required with --layout opencv), e.g. 1024x768.
    #[arg(long, value_parser = parse_size)]
    projector: Option<(u32, u32)>,
    /// Decoder thresholds as JSON (fields of DecodeParams, e.g. '{"min_bit_snr": 4.0}');
    /// unspecified fields keep their defaults.
    #[arg(long)]
    params: Option<String>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let report = match args.layout {
        Layout::Capture => decode_capture(&args)?,
        Layout::Opencv => decode_opencv(&args)?,
    };
    if args.json {
        println!("{report}");
    } else {
        for p in report["projectors"].as_array().into_iter().flatten() {
            eprintln!("{p}");
        }
        eprintln!("artefacts in {}", args.out.display());
    }
    Ok(())
}

fn params_json(args: &Args, defaults: DecodeParams) -> anyhow::Result<serde_json::Value> {
    let mut value = serde_json::to_value(defaults)?;
    if let Some(text) = &args.params {
        let extra: serde_json::Value =
            serde_json::from_str(text).context("--params is not valid JSON")?;
        let Some(fields) = extra.as_object() else {
            bail!("--params must be a JSON object, e.g. '{{\"min_bit_snr\": 4.0}}'");
        };
        for (k, v) in fields {
            if value.get(k).is_none() {
                bail!("--params: unknown decoder parameter `{k}`");
            }
            value[k] = v.clone();
        }
    }
    Ok(value)
}

fn decode_capture(args: &Args) -> anyhow::Result<serde_json::Value> {
    if args.projector.is_some() {
        bail!("--projector is only for --layout opencv (a capture folder knows its projectors)");
    }
    let mut pipeline = Pipeline::new(&args.capture, &args.out, &CalibrationSource::None)
        .with_context(|| format!("opening capture {}", args.capture.display()))?;
    pipeline.set_params("decode", params_json(args, DecodeParams::default())?);
    pipeline.on_stage = Some(Box::new(|name, cached| {
        eprintln!("{name}{}", if cached { " (cached)" } else { " ..." });
    }));
    let report = pipeline.run_until(pipeline::decode_stage::STAGE.name)?;
    let mut out = serde_json::to_value(&report.decode)?;
    out["timing_s"] = serde_json::to_value(&report.timing_s)?;
    Ok(out)
}

fn decode_opencv(args: &Args) -> anyhow::Result<serde_json::Value> {
    let Some(size) = args.projector else {
        bail!("--layout opencv needs --projector WIDTHxHEIGHT (e.g. 1024x768)");
    };
    let params: DecodeParams =
        serde_json::from_value(params_json(args, DecodeParams::for_8_bit())?)?;
    let start = Instant::now();
    let cpu_start = cpu_seconds();
    let frames = code_frames::from_opencv_dir(&args.capture, size)?;
    let loaded = start.elapsed().as_secs_f64();
    let cpu_loaded = cpu_seconds();
    let (decoded, phases) = decode_timed(&frames, size, &params)
        .with_context(|| format!("decoding {}", args.capture.display()))?;
    let decoding = start.elapsed().as_secs_f64() - loaded;
    let cpu_decoded = cpu_seconds();
    // CPU seconds of all threads (10 ms ticks); null where the platform has no probe.
    let cpu = |from: Option<f64>, to: Option<f64>| from.zip(to).map(|(a, b)| b - a);
    pipeline::decode_stage::write_decode(&args.out, 0, &decoded)?;
    Ok(json!({
        "projectors": [pipeline::decode_stage::projector_report(0, &decoded, None)],
        // `decode_phases` splits `decode`: `bits_s` is the part OpenCV's decoding also does.
        "timing_s": { "load": loaded, "decode": decoding, "decode_phases": phases },
        "timing_cpu_s": {
            "load": cpu(cpu_start, cpu_loaded),
            "decode": cpu(cpu_loaded, cpu_decoded),
        },
    }))
}
