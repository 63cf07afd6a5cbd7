//! `mlsss eval`: leave-one-projector-out evaluation of a fitted model on its capture: relight the
//! held-out projector with MLSSS and the baselines, compare with its recorded frames (and with the
//! true subsurface light of a simulated capture).

use std::path::PathBuf;

use anyhow::Context;
use mlsss::capture::Capture;
use mlsss::demo::DemoReport;
use mlsss::demo::html_report::{RelightFigures, write_report};
use mlsss::evaluate::backscatter::evaluate_backscatter;
use mlsss::evaluate::holdout::{HeldOutImages, evaluate_read_holdout};
use mlsss::layer_model::model_file::{Baseline, SubsurfaceModel};
use mlsss::layer_model::render::RenderOptions;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The capture folder the model was fitted on.
    capture: PathBuf,
    /// The model file (`OUT/fit/model.mlsss` of `mlsss process ... --until fit`).
    model: PathBuf,
    /// Projector to relight and compare (default: the one the model was fitted without).
    #[arg(long)]
    holdout: Option<usize>,
    /// Gaussian kernels of the renderer are cut at this many standard deviations.
    #[arg(long, default_value_t = RenderOptions::default().truncate_sigmas,
          value_parser = super::number_arg::positive_finite)]
    truncate_sigmas: f64,
    /// Also write an HTML report with the figures (recorded vs rendered, scanlines).
    #[arg(long, value_name = "FILE")]
    report: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let capture = Capture::open(&args.capture)
        .with_context(|| format!("opening capture {}", args.capture.display()))?;
    let load = || {
        SubsurfaceModel::load(&args.model)
            .with_context(|| format!("loading model {}", args.model.display()))
    };
    // With the projector given, its images are read beside the model's loading (one core
    // inflates the model).
    let (model, images) = match args.holdout {
        Some(k) => {
            let (model, images) = rayon::join(load, || HeldOutImages::read(&capture, k));
            (model?, Some(images?))
        }
        None => (load()?, None),
    };
    let k = args
        .holdout
        .or(model.header.holdout)
        .context("the model was fitted on every projector: pass --holdout K (a projector it did not see is the honest test)")?;
    if model.header.holdout != Some(k) {
        eprintln!(
            "warning: projector {k} was used to fit this model (trained on {:?}): this is not a held-out test",
            model.header.training_projectors
        );
    }
    anyhow::ensure!(
        args.truncate_sigmas > 0.0,
        "--truncate-sigmas must be positive"
    );
    let mut renderers = vec![Baseline::Mlsss, Baseline::Homogeneous];
    if model.dipole.is_some() {
        renderers.push(Baseline::Dipole);
    } else {
        eprintln!("the model has no dipole baseline (fitted with dipole: false): skipping it");
    }
    renderers.push(Baseline::Direct);
    let opts = RenderOptions {
        truncate_sigmas: args.truncate_sigmas,
        ..RenderOptions::default()
    };
    eprintln!("rendering projector {k} under its evaluation patterns ...");
    let images = match images {
        Some(images) => images,
        None => HeldOutImages::read(&capture, k)?,
    };
    let result = evaluate_read_holdout(&capture, images, &model, &renderers, &opts)?;
    let mut relight = result.report.clone();
    // A simulated capture has the true slit light: report the back-scatter split as the demo does.
    if capture.truth_dir().is_some()
        && let Some(b) = evaluate_backscatter(&model, k, &result.slits)?
    {
        relight.backscatter = Some(b.report);
    }
    let report = DemoReport {
        relight: Some(relight),
        ..DemoReport::default()
    };
    if let Some(path) = &args.report {
        let processed = args
            .model
            .parent()
            .and_then(|fit| fit.parent())
            .map(PathBuf::from)
            .unwrap_or_default();
        let figures = RelightFigures {
            images: result.kept.clone(),
            mask: result.mask.clone(),
        };
        write_report(path, &report, Some(&figures), &processed)
            .with_context(|| format!("writing {}", path.display()))?;
        eprintln!("report: {}", path.display());
    }
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        eprintln!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(())
}
