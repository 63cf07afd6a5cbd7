//! `mlsss render`: render a projector's pattern on the measured face from a fitted model file
//! (paper eqs. 3-5, plus the direct part), as linear EXR and a tone-mapped PNG beside it.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use image::Rgb32FImage;
use mlsss::booth::{InvalidPattern, PatternSpec, validate_patterns};
use mlsss::capture::{Axis, Pattern};
use mlsss::imageio;
use mlsss::layer_model::model_file::{Baseline, SubsurfaceModel, render_projector};
use mlsss::layer_model::render::RenderOptions;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The model file written by `mlsss process CAPTURE --calib ... --until fit`
    /// (`OUT/fit/model.mlsss`).
    model: PathBuf,
    /// The light: `projector:K` (K = 0, 1, ...; typically the held-out projector).
    #[arg(long)]
    light: String,
    /// Pattern the projector shows, by its capture label: `white`, `black`, `grey-500` (level in
    /// thousandths), `slit-x-o12` / `slit-y-o0` (slit sweep, offset in px), `gray-x-b3[-inv]`
    /// (Gray-code bit), `hf-s2` (high-frequency stripes, shift in px).
    #[arg(long, default_value = "white")]
    pattern: String,
    /// Output EXR (linear, the frames' units); a tone-mapped PNG is written beside it.
    #[arg(long)]
    out: PathBuf,
    /// Which model renders the subsurface light: the fitted MLSSS model, its skin average
    /// (homogeneous), the per-pixel dipole, or none (direct only).
    #[arg(long, value_enum, default_value_t = Baseline::Mlsss)]
    baseline: Baseline,
    /// Write only the subsurface (global) part instead of direct + global.
    #[arg(long)]
    global_only: bool,
    /// Slit width of `slit-*` patterns (projector px; default: the captured booth's).
    #[arg(long)]
    slit_width: Option<u32>,
    /// Slit period of `slit-*` patterns (projector px; default: the captured booth's).
    #[arg(long)]
    slit_period: Option<u32>,
    /// Stripe width of `hf-*` patterns (projector px; default: the captured booth's).
    #[arg(long)]
    stripe: Option<u32>,
    /// Exposure of the PNG: linear value shown as white (default: the 99th percentile).
    #[arg(long, value_parser = super::number_arg::positive_finite_f32)]
    white: Option<f32>,
    /// Print a JSON object (paths, model, timing) on stdout.
    #[arg(long)]
    json: bool,
}

/// Parses `projector:K`.
fn parse_light(light: &str) -> anyhow::Result<usize> {
    let Some(k) = light.strip_prefix("projector:") else {
        bail!("--light {light}: expected `projector:K`, e.g. `projector:3`");
    };
    k.parse()
        .with_context(|| format!("--light {light}: `{k}` is not a projector number"))
}

/// Parses a pattern label (see `Pattern::label`) and checks it is one the booth can show (with
/// `--slit-width`, `--slit-period` and `--stripe` in place of the booth's values).
fn parse_pattern(label: &str, args: &Args, booth: &PatternSpec) -> anyhow::Result<Pattern> {
    let spec = PatternSpec {
        slit_width_px: args.slit_width.unwrap_or(booth.slit_width_px),
        slit_period_px: args.slit_period.unwrap_or(booth.slit_period_px),
        hf_stripe_px: args.stripe.unwrap_or(booth.hf_stripe_px),
        ..booth.clone()
    };
    if let Err(InvalidPattern { field, reason }) = validate_patterns(&spec) {
        let flag = match field.as_str() {
            "patterns.slit_width_px" => "--slit-width",
            "patterns.slit_period_px" => "--slit-period",
            "patterns.hf_stripe_px" => "--stripe",
            other => other,
        };
        bail!("{flag}: {reason}");
    }
    let pattern = parse_pattern_label(label, &spec)?;
    pattern
        .check_against(&spec)
        .map_err(|reason| anyhow::anyhow!("--pattern {label}: {reason}"))?;
    Ok(pattern)
}

/// The pattern a label names, with the slit and stripe geometry of `spec`.
fn parse_pattern_label(label: &str, spec: &PatternSpec) -> anyhow::Result<Pattern> {
    let axis = |a: &str| match a {
        "x" => Ok(Axis::X),
        "y" => Ok(Axis::Y),
        _ => bail!("--pattern {label}: axis `{a}` must be x or y"),
    };
    let number = |s: &str, what: &str| -> anyhow::Result<u32> {
        s.parse()
            .with_context(|| format!("--pattern {label}: `{s}` is not a {what}"))
    };
    let parts: Vec<&str> = label.split('-').collect();
    Ok(match parts.as_slice() {
        ["white"] => Pattern::White,
        ["black"] => Pattern::Black,
        ["grey", level] => Pattern::Grey {
            level_milli: number(level, "level in thousandths")?,
        },
        ["slit", a, offset] if offset.starts_with('o') => Pattern::Slit {
            axis: axis(a)?,
            width: spec.slit_width_px,
            period: spec.slit_period_px,
            offset: number(&offset[1..], "slit offset")?,
        },
        ["gray", a, bit, rest @ ..] if bit.starts_with('b') && rest.len() <= 1 => {
            let inverted = match rest {
                [] => false,
                ["inv"] => true,
                _ => bail!("--pattern {label}: expected gray-x-bN or gray-x-bN-inv"),
            };
            Pattern::Gray {
                axis: axis(a)?,
                bit: number(&bit[1..], "bit")?,
                inverted,
            }
        }
        ["hf", shift] if shift.starts_with('s') => Pattern::HighFrequency {
            stripe: spec.hf_stripe_px,
            shift: number(&shift[1..], "shift")?,
        },
        _ => bail!(
            "--pattern {label}: unknown pattern (white, black, grey-N, slit-x-oN, slit-y-oN, \
             gray-x-bN[-inv], gray-y-bN[-inv], hf-sN)"
        ),
    })
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let k = parse_light(&args.light)?;
    let png = args.out.with_extension("png");
    super::output_paths::refuse_overlaps(
        &[("MODEL", &args.model)],
        &[("--out", &args.out), ("the PNG beside --out", &png)],
    )?;
    let start = Instant::now();
    let model = SubsurfaceModel::load(&args.model)?;
    let loaded = start.elapsed().as_secs_f64();
    let pattern = parse_pattern(&args.pattern, &args, &model.header.patterns)?;
    let relit = render_projector(
        &model,
        k,
        &pattern,
        args.baseline,
        &RenderOptions::default(),
    )
    .with_context(|| format!("rendering projector {k} with {}", args.model.display()))?;
    let rendered = start.elapsed().as_secs_f64() - loaded;
    let values = if args.global_only {
        relit.global.clone()
    } else {
        relit.total()
    };
    let (w, h) = (model.header.width as u32, model.header.height as u32);
    let img = Rgb32FImage::from_fn(w, h, |x, y| image::Rgb(values[(y * w + x) as usize]));
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    imageio::write_exr_rgb(&args.out, &img)?;
    let white = args.white.unwrap_or_else(|| percentile_99(&values));
    imageio::write_png_preview(&png, &img, white)?;
    let report = serde_json::json!({
        "model": args.model.display().to_string(),
        "projector": k,
        "pattern": pattern.label(),
        "baseline": args.baseline,
        "global_only": args.global_only,
        "exr": args.out.display().to_string(),
        "png": png.display().to_string(),
        "png_white": white,
        "holdout": model.header.holdout,
        "timing_s": { "load": loaded, "render": rendered },
    });
    if args.json {
        println!("{report}");
    } else {
        eprintln!(
            "wrote {} and {} ({:.2} s)",
            args.out.display(),
            png.display(),
            rendered
        );
    }
    Ok(())
}

/// The 99th percentile of the positive values (1 when there are none).
fn percentile_99(values: &[[f32; 3]]) -> f32 {
    let mut v: Vec<f32> = values
        .iter()
        .flat_map(|p| p.iter().copied())
        .filter(|v| v.is_finite() && *v > 0.0)
        .collect();
    if v.is_empty() {
        return 1.0;
    }
    v.sort_by(f32::total_cmp);
    v[(v.len() * 99 / 100).min(v.len() - 1)]
}
