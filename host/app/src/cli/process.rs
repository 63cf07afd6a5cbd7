//! `mlsss process`: run the processing pipeline on a capture up to a stage, printing the report.

use std::path::PathBuf;

use anyhow::Context;
use mlsss::layer_model::fit::EmVariant;
use mlsss::layer_model::surface::ViewRay;
use mlsss::photometry::slit_leak::LeakReading;
use mlsss::pipeline::fit_stage::FitParams;
use mlsss::pipeline::normals_stage::{NormalSource, NormalsParams, PsInput, ShadingModel};
use mlsss::pipeline::profiles_stage::{
    DirectPart, ProfileWeights, ProfilesParams, SlitCoordinates,
};
use mlsss::pipeline::separate_stage::{DirectModel, SeparateParams, SeparationMethod};
use mlsss::pipeline::{self, CalibrationSource, Pipeline};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The capture folder (`capture.json` + `frames/`).
    capture: PathBuf,
    /// Calibration: a calibration JSON file, or `truth` for a simulated capture's
    /// `truth/calibration.json`. Needed from the geometry stage on.
    #[arg(long)]
    calib: Option<String>,
    /// Last stage to run (its inputs run first; cached stages are reused). Stages: decode,
    /// geometry, separate, normals, profiles, fit.
    #[arg(long, default_value = "geometry")]
    until: String,
    /// Fit stage: projector left out of training (for held-out evaluation); default none.
    #[arg(long)]
    holdout: Option<usize>,
    /// Fit stage: EM variant, `layered` (means tied to layer depth, joint over projectors and
    /// axes; ours) or `free` (free means per profile, averaged; the paper).
    #[arg(long, value_enum, default_value_t = EmArg::Layered)]
    em: EmArg,
    /// Fit stage: Gaussian components per fit at the start (the paper: 20); BIC reduces them
    /// per pixel where the profile does not support them.
    #[arg(long, default_value_t = 20)]
    components: usize,
    /// Profiles stage: direct reflection removed from the slit frames, `separation` (the
    /// separate stage's direct image), `colourless` (its smallest channel: skin's surface
    /// reflection is colourless, the subsurface light that leaks into a coarse separation is
    /// not), `none` (all slit light counts as subsurface light) or `auto` (per pixel: the
    /// separation's direct image weighted by the share of the pixel's light it holds, 0 below
    /// `--direct-fraction-range`'s low end, 1 above its high end; none on light skin,
    /// separation on very dark skin, the default before the dichromatic separation).
    #[arg(long, value_enum, default_value_t = DirectArg::Separation)]
    direct: DirectArg,
    /// Profiles stage, `--direct auto`: the direct fractions (low, high) between which the
    /// separated direct light goes from ignored to removed, e.g. `0.25,0.45`.
    #[arg(long, value_delimiter = ',')]
    direct_fraction_range: Option<Vec<f32>>,
    /// Fit stage: fit one pixel per BLOCK x BLOCK tile (1 = every pixel; larger is faster and
    /// coarser).
    #[arg(long, default_value_t = 1)]
    block: usize,
    /// Fit stage: stop a fit's EM when one iteration gains less than this in log-likelihood per
    /// unit weight.
    #[arg(long, default_value_t = FitParams::default().tolerance,
          value_parser = super::number_arg::positive_finite)]
    tolerance: f64,
    /// Fit stage: EM iteration cap per fit.
    #[arg(long, default_value_t = FitParams::default().max_iterations)]
    max_iterations: usize,
    /// Fit stage: with `--holdout` on a simulated capture, also render the held-out projector
    /// against the simulator's truth (`heldout_global_rel_rmse`). Evaluation only, off by
    /// default: `mlsss eval` renders and reports the same figures from the model file (at full
    /// size the renders are ~14 CPU-s of the fit).
    #[arg(long)]
    heldout_check: bool,
    /// The default now (see `--heldout-check`); still accepted so older commands run.
    #[arg(long, hide = true, conflicts_with = "heldout_check")]
    no_heldout_check: bool,
    /// Fit stage: skip the per-pixel dipole baseline (Jensen 2001). It is an evaluation baseline,
    /// not part of the MLSSS model; `mlsss eval` then reports no dipole numbers.
    #[arg(long)]
    no_dipole: bool,
    /// Fit stage: keep each pixel's own fitted layers instead of the spatial prior (shapes pooled
    /// over neighbouring tiles, amplitudes shrunk toward the subject's mean, both as far as
    /// cross-validation on the training projectors says; `subsurface::spatial_prior`).
    #[arg(long)]
    no_spatial_prior: bool,
    /// Fit stage: keep the normals stage's normals instead of correcting them by the shading
    /// regression of the training projectors' subsurface amplitudes (strength chosen by
    /// leave-one-projector-out cross-validation; `subsurface::shading_regression`).
    #[arg(long)]
    no_normal_refinement: bool,
    /// Profiles stage: where the camera sees a layer at depth, `exit-point` (where the light
    /// leaves the surface: no view term, diffuse emergence), `refracted` (along the refracted
    /// view ray) or `unrefracted` (paper eq. 5). See `subsurface::layer_depth`.
    #[arg(long, value_enum)]
    view_ray: Option<ViewRayArg>,
    /// Profiles stage: projector coordinates the slit distances are measured in, `projected`
    /// (the surface point projected through the calibration, as every render places a light) or
    /// `decoded` (the Gray-code coordinates; subsurface light moves them toward the light).
    #[arg(long, value_enum, default_value_t = CoordinatesArg::Projected)]
    slit_coordinates: CoordinatesArg,
    /// Profiles stage: how the layer fits weigh a pixel's profiles, `information` (by the
    /// effective photons each carries under the camera's noise model at its projector's
    /// exposure) or `equal` (the paper's pooling).
    #[arg(long, value_enum, default_value_t = ProfileWeightsArg::Information)]
    profile_weights: ProfileWeightsArg,
    /// Profiles stage, simulated captures: also extract the slit frames by the other rules
    /// (hard slit edges, each `--direct` rule) and report each one's error against the truth
    /// (`slit_global_rel_rmse_*`; decodes the slit frames again).
    #[arg(long)]
    compare_slit_variants: bool,
    /// Fit stage: fixed layer spacing D (mm, > 0) instead of the subject-wide estimate.
    #[arg(long, value_parser = super::number_arg::positive_finite)]
    depth_spacing: Option<f64>,
    /// Separate stage: `kernel` (ours: the global light's stripe contrast, measured from the
    /// slit sweep, removed from the direct part) or `nayar` (Nayar et al. 2006, the baseline).
    #[arg(long, value_enum, default_value_t = SeparationArg::Kernel)]
    separation: SeparationArg,
    /// Separate stage, `kernel`: Gaussian sigma (camera px) over which the colourless direct part
    /// is averaged (0: per pixel).
    #[arg(long, default_value_t = SeparateParams::default().direct_smoothing_px,
          value_parser = super::number_arg::non_negative_finite)]
    direct_smoothing: f64,
    /// Separate stage, `kernel`: how each pixel's kernel leak is read from its slit profile,
    /// `harmonics` (the sweep's harmonics around the stripe frequency: exact for the profile,
    /// the skin's direct reflection included) or `cosine` (a cosine at the stripe frequency about
    /// the brightest slit, the method before).
    #[arg(long, value_enum, default_value_t = LeakReadingArg::Harmonics)]
    leak_reading: LeakReadingArg,
    /// Separate stage, `kernel`: how the direct part is read from the leak-corrected split,
    /// `lobe` (the surface's specular lobe from the geometry and the calibration, combined with
    /// the colour estimate; body colour per band of incidence), `dichromatic` (a colourless
    /// reflection plus one body colour read from the split's global part, the method before) or
    /// `colourless` (the mean of the channels' direct parts).
    #[arg(long, value_enum, default_value_t = DirectModelArg::Lobe)]
    direct_model: DirectModelArg,
    /// Normals stage: the images photometric stereo reads, `nayar-direct` (the Nayar baseline's
    /// direct part, whatever `--separation` says), `white` (the stray-free white frames),
    /// `direct` (the separation's direct part) or `global` (the separation's global part: white
    /// less the direct part).
    #[arg(long, value_enum, default_value_t = PsInputArg::White)]
    ps_input: PsInputArg,
    /// Normals stage: the shading model, `specular` (skin's Fresnel transmittance plus the
    /// surface's specular lobe, `photometry::specular_ps`), `transmission` (the transmittance
    /// alone, `photometry::transmission_ps`) or `lambertian`.
    #[arg(long, value_enum, default_value_t = PsModelArg::Specular)]
    ps_model: PsModelArg,
    /// Normals stage: the Lambertian model (short for `--ps-model lambertian`).
    #[arg(long, conflicts_with = "ps_model")]
    lambertian_ps: bool,
    /// Normals stage: `fused` (the geometry's low spatial frequencies with photometric stereo's
    /// detail, `photometry::normal_fusion`) or `photometric` (photometric stereo alone).
    #[arg(long, value_enum, default_value_t = NormalSourceArg::Fused)]
    normals_source: NormalSourceArg,
    /// Output folder: one sub-folder per stage, plus report.json.
    #[arg(long)]
    out: PathBuf,
    /// Print the report as one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

/// `--direct-model` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum DirectModelArg {
    Lobe,
    Dichromatic,
    Colourless,
}

/// `--leak-reading` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum LeakReadingArg {
    Cosine,
    Harmonics,
}

/// EM variants (DESIGN section 5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum EmArg {
    Layered,
    Free,
}

/// View-ray models (`subsurface::surface::ViewRay`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum ViewRayArg {
    ExitPoint,
    Refracted,
    Unrefracted,
}

/// Slit coordinates (`pipeline::profiles_stage::SlitCoordinates`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum CoordinatesArg {
    Projected,
    Decoded,
}

/// Profile weights (`pipeline::profiles_stage::ProfileWeights`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum ProfileWeightsArg {
    Information,
    Equal,
}

/// Separation methods (`pipeline::separate_stage::SeparationMethod`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum SeparationArg {
    Kernel,
    Nayar,
}

/// Photometric-stereo shading models (`pipeline::normals_stage::ShadingModel`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum PsModelArg {
    Specular,
    Transmission,
    Lambertian,
}

/// What the normals stage's normals are (`pipeline::normals_stage::NormalSource`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum NormalSourceArg {
    Fused,
    Photometric,
}

/// Photometric-stereo inputs (`pipeline::normals_stage::PsInput`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum PsInputArg {
    NayarDirect,
    White,
    Direct,
    Global,
}

/// Direct part of the slit frames (see `pipeline::profiles_stage::DirectPart`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum DirectArg {
    Separation,
    Colourless,
    None,
    Auto,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let calib = match args.calib.as_deref() {
        None => CalibrationSource::None,
        Some("truth") => CalibrationSource::Truth,
        Some(path) => CalibrationSource::File(PathBuf::from(path)),
    };
    let mut pipeline = Pipeline::new(&args.capture, &args.out, &calib)
        .with_context(|| format!("opening {}", args.capture.display()))?;
    let fit = FitParams {
        holdout: args.holdout,
        em: match args.em {
            EmArg::Layered => EmVariant::Layered,
            EmArg::Free => EmVariant::Free,
        },
        components: args.components,
        block: args.block,
        tolerance: args.tolerance,
        max_iterations: args.max_iterations,
        heldout_check: args.heldout_check && !args.no_heldout_check,
        dipole: !args.no_dipole,
        spatial_prior: !args.no_spatial_prior,
        refine_normals: !args.no_normal_refinement,
        depth_spacing_mm: args.depth_spacing,
    };
    pipeline.set_params("fit", serde_json::to_value(&fit)?);
    let profiles = ProfilesParams {
        direct: match args.direct {
            DirectArg::Separation => DirectPart::Separation,
            DirectArg::Colourless => DirectPart::Colourless,
            DirectArg::None => DirectPart::None,
            DirectArg::Auto => DirectPart::Auto,
        },
        direct_fraction_range: match args.direct_fraction_range.as_deref() {
            None => mlsss::pipeline::profiles_stage::DEFAULT_DIRECT_FRACTION_RANGE,
            Some([lo, hi]) if lo <= hi => (*lo, *hi),
            Some(other) => anyhow::bail!("--direct-fraction-range wants LOW,HIGH, got {other:?}"),
        },
        view_ray: match args.view_ray {
            None => ProfilesParams::default().view_ray,
            Some(ViewRayArg::ExitPoint) => ViewRay::ExitPoint,
            Some(ViewRayArg::Refracted) => ViewRay::Refracted,
            Some(ViewRayArg::Unrefracted) => ViewRay::Unrefracted,
        },
        coordinates: match args.slit_coordinates {
            CoordinatesArg::Projected => SlitCoordinates::Projected,
            CoordinatesArg::Decoded => SlitCoordinates::Decoded,
        },
        weights: match args.profile_weights {
            ProfileWeightsArg::Information => ProfileWeights::Information,
            ProfileWeightsArg::Equal => ProfileWeights::Equal,
        },
        compare_variants: args.compare_slit_variants,
        ..ProfilesParams::default()
    };
    pipeline.set_params("profiles", serde_json::to_value(&profiles)?);
    let separate = SeparateParams {
        method: match args.separation {
            SeparationArg::Kernel => SeparationMethod::Kernel,
            SeparationArg::Nayar => SeparationMethod::Nayar,
        },
        direct_smoothing_px: args.direct_smoothing,
        leak_reading: match args.leak_reading {
            LeakReadingArg::Cosine => LeakReading::Cosine,
            LeakReadingArg::Harmonics => LeakReading::Harmonics,
        },
        direct_model: match args.direct_model {
            DirectModelArg::Lobe => DirectModel::Lobe,
            DirectModelArg::Dichromatic => DirectModel::Dichromatic,
            DirectModelArg::Colourless => DirectModel::Colourless,
        },
        ..SeparateParams::default()
    };
    pipeline.set_params("separate", serde_json::to_value(&separate)?);
    let normals = NormalsParams {
        input: match args.ps_input {
            PsInputArg::NayarDirect => PsInput::NayarDirect,
            PsInputArg::White => PsInput::White,
            PsInputArg::Direct => PsInput::Direct,
            PsInputArg::Global => PsInput::Global,
        },
        model: match (args.lambertian_ps, args.ps_model) {
            (true, _) | (false, PsModelArg::Lambertian) => ShadingModel::Lambertian,
            (false, PsModelArg::Transmission) => ShadingModel::Transmission,
            (false, PsModelArg::Specular) => ShadingModel::Specular,
        },
        source: match args.normals_source {
            NormalSourceArg::Fused => NormalSource::Fused,
            NormalSourceArg::Photometric => NormalSource::Photometric,
        },
        ..NormalsParams::default()
    };
    pipeline.set_params("normals", serde_json::to_value(&normals)?);
    pipeline.on_stage = Some(Box::new(|name, cached| {
        eprintln!("{name}{}", if cached { " (cached)" } else { " ..." });
    }));
    let report = with_separation_alias(serde_json::to_value(pipeline.run_until(&args.until)?)?);
    if let Some(k) = args.holdout
        && args.until == "fit"
        && !args.heldout_check
    {
        // The held-out figures are the evaluation's; say where they come from now that the fit
        // no longer renders them by default.
        eprintln!(
            "held-out projector {k}: `mlsss eval {} {} --holdout {k}` reports its errors \
             (or rerun with --heldout-check)",
            args.capture.display(),
            mlsss::pipeline::fit_stage::model_path(&args.out).display()
        );
    }
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        eprintln!(
            "report in {}",
            args.out.join(pipeline::REPORT_FILE).display()
        );
        eprintln!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(())
}

/// The report with the `separate` fragment also under `separation`, the key the demo prints the
/// same numbers under, so one name works for both commands.
fn with_separation_alias(mut report: serde_json::Value) -> serde_json::Value {
    if let Some(object) = report.as_object_mut()
        && let Some(separate) = object.get("separate").cloned()
    {
        object.insert("separation".into(), separate);
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn separation_alias_repeats_the_separate_fragment() {
        let report = serde_json::json!({ "separate": { "global_rel_rmse": 0.1 }, "decode": {} });
        let aliased = with_separation_alias(report);
        assert_eq!(aliased["separation"]["global_rel_rmse"], 0.1);
        assert_eq!(aliased["separate"]["global_rel_rmse"], 0.1);
        let without = with_separation_alias(serde_json::json!({ "decode": {} }));
        assert!(without.get("separation").is_none());
    }
}
