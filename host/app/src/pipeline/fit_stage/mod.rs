//! Stage `fit` (DESIGN stage 7): the layer model of every skin pixel from the slit profiles of the
//! training projectors (`subsurface::fit`), saved as one model file with what rendering needs
//! (`subsurface::model_file`).
//!
//! - Training projectors: every decoded projector but `holdout`.
//! - Pixels skipped: off the subject, and not lit by any training projector or with no light in
//!   their profiles (shadowed, background). Surface pixels left without a fit (e.g. lit only by the
//!   held-out projector) get the subject's mean layers, so a render has no holes; counted in
//!   `pixels_filled`.
//! - The per-pixel dipole baseline is fitted on the same profiles and stored in the model file.
//!
//! Artefacts in `OUT/fit/`:
//! - `model.mlsss`: the model file (see `subsurface::model_file`).
//! - `fig10.svg`, `fig10.png`: the paper's Fig. 10 for this scene: R channel along the scanline of
//!   the profiles stage under a slit of the held-out projector (or projector 0 without holdout),
//!   measured global light against the model's, the homogeneous model's and, for a simulated
//!   capture, the truth.
//! - `pixel_profiles.svg`, `pixel_profiles.png`: three scanline pixels' profile samples (R, first
//!   training projector, along x) against the fitted model's profile.
//! - `fig10.json`: the data of both plots (for the HTML report).
//!
//! Report fragment: `components_mean`, `depth_spacing_mm`, `depth_estimate`, `pixels_fitted`,
//! `pixels_skipped`, `pixels_filled`, `fits`, `mean_iterations`, `em`, `components`, `holdout`,
//! `training_projectors`, `model_file`, `model_bytes`,
//! `timing_s.{load,fit,fit_normals,fit_em,fit_prior,dipole,heldout,save,figures}` (wall; `load`
//! takes the profiles' inputs and extracts the training projectors' slit frames; `fit` ends with
//! the model, its parts are the normals' shading correction, the EM, then the spatial
//! prior while the dipole baseline is fitted beside it; `heldout` is the held-out renders; the
//! model is saved, then the figures are drawn) and
//! `timing_cpu_s.{load,fit,fit_normals,fit_em,prior_and_dipole,heldout,save_and_figures}`
//! (CPU, all threads),
//! and with a holdout on a simulated capture (unless `heldout_check` is off)
//! `heldout_global_rel_rmse.{pattern}.{mlsss,homogeneous,dipole}`: relative RMS error of the held-out projector's rendered subsurface light
//! against the simulator's, over the pixels that projector lights.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use super::line_plot::{LinePlot, LinePlotError, Mark, Series};
use super::profiles_stage::{ProfileInputs, ProfilesRecord, ProfilesStageError, true_slit_global};
use super::{Stage, StageContext, StageFailure};
use mlsss_core::capture::{Axis, Pattern, truth};
use mlsss_core::imageio::{self, ImageIoError};
use mlsss_core::resources::cpu_seconds;
use mlsss_layer_model::fit::{EmVariant, FitError, FitOptions, fit_dipole_model, fit_model};
use mlsss_layer_model::layer_depth::SpacingEstimate;
use mlsss_layer_model::mixture::{EmConfig, Profile};
use mlsss_layer_model::model_file::{
    Baseline, FORMAT_VERSION, ModelFileError, ModelHeader, ProjectorLight, ProjectorPatterns,
    SubsurfaceModel, render_pattern_alone,
};
use mlsss_layer_model::profiles::{
    GeometryMap, ProfileError, SlitStack, SlitSweep, pixel_geometry,
};
use mlsss_layer_model::relight::{direct_albedo, pattern_irradiance};
use mlsss_layer_model::render::{LayerModel, RenderOptions, SplatLayer, extent};
use mlsss_layer_model::shading_regression::{ShadingReport, refine_normals};
use mlsss_layer_model::spatial_prior::regularise_in_place;
use mlsss_layer_model::surface::Surface;

mod figures;

#[cfg(test)]
use figures::model_profile;
use figures::{PreparedFigures, fig10_measured, prepare_figures, write_figures};

/// The fit stage.
pub const STAGE: Stage = Stage {
    name: "fit",
    version: 2,
    inputs: &["profiles"],
    uses_calibration: true,
    run,
};

/// Name of the model file in the stage folder.
pub const MODEL_FILE: &str = "model.mlsss";

/// Path of the model file in an output folder.
pub fn model_path(out: &Path) -> PathBuf {
    out.join("fit").join(MODEL_FILE)
}

/// Parameters of the fit stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FitParams {
    /// Projector left out of training (for held-out evaluation).
    pub holdout: Option<usize>,
    pub em: EmVariant,
    /// Components per fit at the start (the paper: 20); BIC reduces them per pixel.
    pub components: usize,
    /// EM iteration cap and tolerance (log-likelihood gain per unit weight). 1e-5 stops after
    /// ~19 iterations with warm starts. Looser tolerances keep the whole held-out error but lose
    /// the back-scatter (2026-11-23, projector 3 held out, 4 components, 6 px blocks, full-size
    /// head): 1e-5 / 3e-5 / 1e-4 take 19 / 12 / 7 iterations for `relight.global_rel_rmse`
    /// 0.1337 / 0.1336 / 0.1335, but the subsurface light's toward/away-from-the-light ratio
    /// moves from 0.901 to 0.924 and 0.943 (truth 0.852) and the error on the side toward the
    /// light grows from 0.210 to 0.221 and 0.230: the last iterations fit the deep layers that
    /// carry the asymmetry. 1e-7 took ~74 iterations on the quick head for the same error.
    pub max_iterations: usize,
    pub tolerance: f64,
    /// Fit one pixel per `block x block` tile (1 = every pixel).
    pub block: usize,
    /// Fixed layer spacing D (mm) instead of estimating it.
    pub depth_spacing_mm: Option<f64>,
    /// Also fit the per-pixel dipole baseline.
    pub dipole: bool,
    /// With a holdout on a simulated capture, render the held-out projector (white and both
    /// slits, every model: 9 renders) for `heldout_global_rel_rmse`. `mlsss eval` and the demo
    /// render the same images again, so the demo turns this off.
    pub heldout_check: bool,
    /// Regularise the per-pixel layers with the spatial prior (`subsurface::spatial_prior`).
    pub spatial_prior: bool,
    /// Correct the normals by the shading regression of the training projectors' amplitudes
    /// (`subsurface::shading_regression`) before fitting.
    pub refine_normals: bool,
}

impl Default for FitParams {
    fn default() -> Self {
        Self {
            holdout: None,
            em: EmVariant::Layered,
            components: 20,
            max_iterations: 200,
            tolerance: 1e-5,
            block: 1,
            depth_spacing_mm: None,
            dipole: true,
            heldout_check: true,
            spatial_prior: true,
            refine_normals: true,
        }
    }
}

/// Errors of the fit stage.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FitStageError {
    /// Rebuilding the profiles failed.
    #[error(transparent)]
    Profiles(#[from] ProfilesStageError),
    /// A slit sweep could not be built.
    #[error(transparent)]
    Profile(#[from] ProfileError),
    /// The EM fit failed.
    #[error(transparent)]
    Fit(#[from] FitError),
    /// The model file could not be written, or a check render failed.
    #[error(transparent)]
    Model(#[from] ModelFileError),
    /// A truth image could not be read.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// A plot could not be written.
    #[error(transparent)]
    Plot(#[from] LinePlotError),
    /// The spatial prior failed.
    #[error(transparent)]
    Prior(#[from] mlsss_layer_model::spatial_prior::SpatialPriorError),
    /// The shading regression failed.
    #[error(transparent)]
    Shading(#[from] mlsss_layer_model::shading_regression::ShadingError),
    /// The holdout names no projector of the capture.
    #[error("--holdout {holdout}: the capture has projectors 0..{count}")]
    BadHoldout { holdout: usize, count: usize },
    /// Every projector is held out or undecoded.
    #[error("no training projector: every projector is held out or has no decoded pixel")]
    NoTrainingProjector,
    /// The held-out check has no light to compare with (the held-out projector's frames are
    /// black, or none of its pixels was decoded).
    #[error(
        "held-out check: projector {projector} shows no subsurface light under `{pattern}` where \
         it was decoded (black or missing frames?); its error would read 0 for every model. \
         Check the capture, or leave out --heldout-check"
    )]
    NothingToCompare { projector: usize, pattern: String },
    /// A parameter is out of range.
    #[error("invalid fit parameter: {0}")]
    BadParameter(&'static str),
    /// The data file could not be written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

fn run(ctx: &StageContext) -> Result<Value, StageFailure> {
    let params: FitParams = ctx.params()?;
    super::fragment(&run_fit(ctx, &params).map_err(StageFailure::new)?)
}

fn check_params(params: &FitParams, captured: usize) -> Result<(), FitStageError> {
    if let Some(h) = params.holdout
        && h >= captured
    {
        return Err(FitStageError::BadHoldout {
            holdout: h,
            count: captured,
        });
    }
    if params.components == 0 || params.components > 64 {
        return Err(FitStageError::BadParameter("components must be in 1..=64"));
    }
    if params.block == 0 {
        return Err(FitStageError::BadParameter("block must be >= 1"));
    }
    if params.max_iterations == 0 {
        return Err(FitStageError::BadParameter("max_iterations must be >= 1"));
    }
    // NaN never compares below the gain, so the EM would run to the cap in every fit.
    if !(params.tolerance.is_finite() && params.tolerance > 0.0) {
        return Err(FitStageError::BadParameter(
            "tolerance must be a finite number > 0 (e.g. 1e-5)",
        ));
    }
    if let Some(d) = params.depth_spacing_mm
        && !(d.is_finite() && d > 0.0 && d <= MAX_DEPTH_SPACING_MM)
    {
        return Err(FitStageError::BadParameter(
            "depth spacing must be a finite number of mm in (0, 10] (layers are below the surface)",
        ));
    }
    Ok(())
}

/// Largest layer spacing `--depth-spacing` takes, mm: 20 layers 10 mm apart reach 200 mm,
/// far beyond where light comes back out of skin.
const MAX_DEPTH_SPACING_MM: f64 = 10.0;

/// The fit stage's report fragment (see the module documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitReport {
    pub em: EmVariant,
    /// Components per fit at the start.
    pub components: usize,
    /// Mean components per fit after BIC.
    pub components_mean: f64,
    pub depth_spacing_mm: f64,
    pub depth_estimate: SpacingEstimate,
    pub pixels_fitted: usize,
    /// Surface pixels without a fit (filled with the subject's mean layers).
    pub pixels_skipped: usize,
    pub pixels_filled: usize,
    pub fits: usize,
    pub mean_iterations: f64,
    pub holdout: Option<usize>,
    pub training_projectors: Vec<usize>,
    pub model_file: String,
    pub model_bytes: u64,
    /// The spatial prior's report (`subsurface::spatial_prior::PriorReport`, null when off).
    pub spatial_prior: Value,
    /// The shading regression's report (`subsurface::shading_regression::ShadingReport`, null
    /// when off).
    pub shading: Value,
    /// Pattern label to renderer (`mlsss`, `homogeneous`, `dipole`) to relative RMS error of the
    /// held-out projector's rendered subsurface light.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heldout_global_rel_rmse: Option<BTreeMap<String, BTreeMap<String, f64>>>,
    pub timing_s: FitTimings,
    pub timing_cpu_s: FitCpuTimings,
}

/// Wall-clock seconds of the fit stage's parts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct FitTimings {
    pub load: f64,
    /// Up to the model: normals, EM, then the prior beside the dipole baseline.
    pub fit: f64,
    pub fit_normals: f64,
    pub fit_em: f64,
    /// Side by side, each its own wall clock: the spatial prior (with the filling of unfitted
    /// pixels) and the dipole baseline.
    pub fit_prior: f64,
    pub dipole: f64,
    /// The held-out projector's renders against the truth (`heldout_global_rel_rmse`).
    #[serde(default)]
    pub heldout: f64,
    /// Saving the model, then drawing the figures.
    pub save: f64,
    pub figures: f64,
}

/// CPU seconds (all threads) of the fit stage's parts, where the platform tells; what ran side
/// by side is one figure.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct FitCpuTimings {
    pub load: Option<f64>,
    pub fit: Option<f64>,
    pub fit_normals: Option<f64>,
    pub fit_em: Option<f64>,
    pub prior_and_dipole: Option<f64>,
    /// The model's assembly and the held-out renders.
    #[serde(default)]
    pub heldout: Option<f64>,
    pub save_and_figures: Option<f64>,
}

/// CPU seconds between two readings of [`cpu_seconds`].
fn cpu_span(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    a.zip(b).map(|(a, b)| b - a)
}

/// Per training projector, per pixel: the profile geometry.
type Geometries = Vec<GeometryMap>;

/// The training projectors' profile geometry and slit sweeps, borrowed from the inputs.
struct TrainingProfiles<'a> {
    geometries: Vec<GeometryMap>,
    sweeps: Vec<SlitSweep<'a>>,
}

impl<'a> TrainingProfiles<'a> {
    /// The training projectors' slit sweeps, borrowed from `inputs`, beside their `geometries`;
    /// with their flux sums, as the EM's amplitudes and the spatial prior's read every pixel's.
    fn new(
        inputs: &'a ProfileInputs,
        training: &[usize],
        geometries: Geometries,
    ) -> Result<Self, FitStageError> {
        Ok(Self {
            sweeps: training
                .iter()
                .map(|&k| {
                    inputs.projectors[k]
                        .sweep()
                        .map(SlitSweep::with_flux_totals)
                })
                .collect::<Result<_, _>>()?,
            geometries,
        })
    }
}

/// The layers fitted to every pixel, regularised and filled, with the dipole baseline.
struct FittedLayers {
    layers: LayerModel,
    dipole: Option<LayerModel>,
    summary: FitSummary,
}

/// What the report says of the fitted layers.
struct FitSummary {
    stats: mlsss_layer_model::fit::FitStats,
    prior: Option<mlsss_layer_model::spatial_prior::PriorReport>,
    /// Per pixel: fitted (before filling).
    fitted: Vec<bool>,
    filled: usize,
    em_s: f64,
    prior_s: f64,
    dipole_s: f64,
    /// CPU reading when the EM ended and the prior and dipole began.
    cpu_after_em: Option<f64>,
}

/// What the fit stage gathered as it ran, for [`FitReport::new`].
struct FitOutcome {
    training: Vec<usize>,
    shading: Option<ShadingReport>,
    fit: FitSummary,
    heldout: Option<BTreeMap<String, BTreeMap<String, f64>>>,
    model_file: PathBuf,
    model_bytes: u64,
    timing_s: FitTimings,
    timing_cpu_s: FitCpuTimings,
}

impl FitReport {
    /// The report of a fit with `params` over the surface `mask`.
    fn new(params: &FitParams, mask: &[bool], outcome: FitOutcome) -> Self {
        let FitOutcome {
            training,
            shading,
            fit,
            heldout,
            model_file,
            model_bytes,
            timing_s,
            timing_cpu_s,
        } = outcome;
        let stats = &fit.stats;
        Self {
            em: params.em,
            components: params.components,
            components_mean: stats.mean_layers,
            depth_spacing_mm: stats.depth_spacing_mm,
            depth_estimate: stats.depth.clone(),
            pixels_fitted: fit.fitted.iter().filter(|f| **f).count(),
            pixels_skipped: mask
                .iter()
                .zip(&fit.fitted)
                .filter(|(m, f)| **m && !**f)
                .count(),
            pixels_filled: fit.filled,
            fits: stats.fits,
            mean_iterations: stats.mean_iterations,
            holdout: params.holdout,
            training_projectors: training,
            model_file: model_file.display().to_string(),
            model_bytes,
            spatial_prior: serde_json::to_value(&fit.prior).unwrap_or(Value::Null),
            shading: serde_json::to_value(&shading).unwrap_or(Value::Null),
            heldout_global_rel_rmse: heldout,
            timing_s,
            timing_cpu_s,
        }
    }
}

/// Runs the fit. Memory the stage frees stays with the allocator for its next phase: handing it
/// back between phases (`malloc_trim`, five calls) kept the peak down while the spatial prior's
/// and the dipole's models were written out layer by layer (1.81-1.85 GiB at full size), but
/// every page handed back was faulted in again by the next phase (on the build VM, memory handed
/// back costs up to 1.3 s per GiB to fault in once the hypervisor has taken it). With the models'
/// rows sharing their shapes the peak is 1.5 GiB handing back and 1.6-1.7 GiB keeping. Shared
/// rows and memory kept against 11e24a9 (`scripts/race_builds.sh`, 3 cycles, full-size
/// `process --until fit`): fit stage 7.14 -> 6.33 s, whole run 26.7 -> 25.7 CPU-s, peak 1.83 ->
/// 1.68 GiB (medians; largest peak).
fn run_fit(ctx: &StageContext, params: &FitParams) -> Result<FitReport, FitStageError> {
    let captured = ctx.capture.manifest.booth.projectors.len();
    check_params(params, captured)?;
    let record = ProfilesRecord::load(&ctx.stage_dir("profiles"))?;
    let t0 = Instant::now();
    let c0 = cpu_seconds();
    let (mut inputs, training) = load_training(ctx, params, &record)?;
    let load_s = t0.elapsed().as_secs_f64();
    let c1 = cpu_seconds();

    let t1 = Instant::now();
    let (geometries, shading) = training_geometry(&mut inputs, &training, params)?;
    // What the model file and the figures take from the projectors' images (on the corrected
    // normals), so the images are freed before the EM.
    let products = ProjectorProducts::new(&inputs, &training);
    let fig10 = fig10_measured(ctx, &inputs, params.holdout, &training)?;
    release_projector_images(&mut inputs);
    let profiles = TrainingProfiles::new(&inputs, &training, geometries)?;
    let normals_s = t1.elapsed().as_secs_f64();
    let c_em = cpu_seconds();
    let FittedLayers {
        layers,
        dipole,
        summary: fit,
    } = fit_layers(&inputs.surface, &profiles, params, record.params.eta)?;
    let fit_s = t1.elapsed().as_secs_f64();
    let c2 = cpu_seconds();

    // What the figures need of the profiles, taken now: the profiles (the training slits and
    // their geometry, 1.4 GB at full size) are freed before the held-out renders and the save.
    let prepared = prepare_figures(
        &inputs,
        &record,
        &layers,
        fig10,
        &training,
        (&profiles.sweeps, &profiles.geometries),
    );
    drop(profiles);
    release_slits(&mut inputs);
    let inputs = inputs;

    let model = assemble(
        ctx,
        &inputs,
        params,
        &training,
        (layers, dipole),
        products,
        &fit.stats,
    )?;
    let t_heldout = Instant::now();
    let heldout = match (params.holdout, ctx.truth_dir(), params.heldout_check) {
        (Some(h), Some(t), true) => Some(heldout_errors(&model, h, &t)?),
        _ => None,
    };
    let heldout_s = t_heldout.elapsed().as_secs_f64();
    let c3 = cpu_seconds();
    let path = ctx.dir().join(MODEL_FILE);
    let (save_s, figures_s) = save_and_draw(ctx, &inputs, &record, &model, prepared, &path)?;
    let model_bytes = std::fs::metadata(&path).map_or(0, |m| m.len());
    let c4 = cpu_seconds();

    let timing_s = FitTimings {
        load: load_s,
        fit: fit_s,
        fit_normals: normals_s,
        fit_em: fit.em_s,
        fit_prior: fit.prior_s,
        dipole: fit.dipole_s,
        heldout: heldout_s,
        save: save_s,
        figures: figures_s,
    };
    let timing_cpu_s = FitCpuTimings {
        load: cpu_span(c0, c1),
        fit: cpu_span(c1, c2),
        fit_normals: cpu_span(c1, c_em),
        fit_em: cpu_span(c_em, fit.cpu_after_em),
        prior_and_dipole: cpu_span(fit.cpu_after_em, c2),
        heldout: cpu_span(c2, c3),
        save_and_figures: cpu_span(c3, c4),
    };
    let outcome = FitOutcome {
        training,
        shading,
        fit,
        heldout,
        model_file: path,
        model_bytes,
        timing_s,
        timing_cpu_s,
    };
    Ok(FitReport::new(params, &inputs.surface.mask, outcome))
}

/// The training projectors' profile geometry, moved out of `inputs`, with the normals first
/// corrected by the shading regression when `params` asks (and its report).
fn training_geometry(
    inputs: &mut ProfileInputs,
    training: &[usize],
    params: &FitParams,
) -> Result<(Geometries, Option<ShadingReport>), FitStageError> {
    // Moved out, not cloned (375 MB at full size); nothing downstream reads them from `inputs`.
    let mut geometries: Geometries = training
        .iter()
        .map(|&k| std::mem::take(&mut inputs.projectors[k].geometry))
        .collect();
    let shading = if params.refine_normals {
        Some(refine_surface(inputs, training, &mut geometries)?)
    } else {
        None
    };
    Ok((geometries, shading))
}

/// The profiles' inputs with the slits of every candidate training projector (all but the
/// holdout), and the training projectors: the candidates with a profile geometry.
fn load_training(
    ctx: &StageContext,
    params: &FitParams,
    record: &ProfilesRecord,
) -> Result<(ProfileInputs, Vec<usize>), FitStageError> {
    let captured = ctx.capture.manifest.booth.projectors.len();
    let candidates: Vec<usize> = (0..captured)
        .filter(|&k| Some(k) != params.holdout)
        .collect();
    let inputs = ProfileInputs::take_or_load(ctx, &record.params, &candidates)?;
    let training: Vec<usize> = candidates
        .into_iter()
        .filter(|&k| inputs.projectors[k].geometry.lit_count() > 0)
        .collect();
    if training.is_empty() {
        return Err(FitStageError::NoTrainingProjector);
    }
    // The other projectors' profile geometry (the held-out one's: 125 MB at full size) is never
    // read by the fit.
    let mut inputs = inputs;
    for p in &mut inputs.projectors {
        if !training.contains(&p.k) {
            p.geometry = GeometryMap::default();
        }
    }
    Ok((inputs, training))
}

/// Corrects the surface normals by the shading regression of the training projectors'
/// amplitudes and recomputes their profile geometry. Everything downstream (fit, prior, dipole,
/// albedo, the model file) sees the corrected normals, so every renderer and baseline gets the
/// same geometry.
fn refine_surface(
    inputs: &mut ProfileInputs,
    training: &[usize],
    geometries: &mut Vec<GeometryMap>,
) -> Result<ShadingReport, FitStageError> {
    // With their flux sums: the regression reads every pixel's flux under every projector.
    let sweeps: Vec<SlitSweep> = training
        .iter()
        .map(|&k| {
            inputs.projectors[k]
                .sweep()
                .map(SlitSweep::with_flux_totals)
        })
        .collect::<Result<_, _>>()?;
    let centres: Vec<Vector3<f64>> = training
        .iter()
        .map(|&k| inputs.projectors[k].centre)
        .collect();
    let report = refine_normals(&mut inputs.surface, geometries, &sweeps, &centres)?;
    drop(sweeps);
    // Freed before the corrected geometry is built, so the two are never held together
    // (375 MB each at full size).
    *geometries = Vec::new();
    *geometries = training
        .iter()
        .map(|&k| {
            pixel_geometry(
                &inputs.surface,
                &inputs.projectors[k].view(),
                inputs.params.eta,
                inputs.params.view_ray,
            )
        })
        .collect::<Result<_, _>>()?;
    Ok(report)
}

/// The EM fit of every pixel, then the spatial prior (and the filling of unfitted pixels) beside
/// the dipole baseline.
fn fit_layers(
    surface: &Surface,
    profiles: &TrainingProfiles,
    params: &FitParams,
    eta: f64,
) -> Result<FittedLayers, FitStageError> {
    let opts = FitOptions {
        em: EmConfig {
            components: params.components,
            max_iterations: params.max_iterations,
            tolerance: params.tolerance,
            squarem: true,
            // See `EmConfig::bic_min_components`.
            bic_min_components: 2,
            ..EmConfig::default()
        },
        variant: params.em,
        depth_spacing: params.depth_spacing_mm,
        block: params.block,
        ..FitOptions::default()
    };
    let (geometries, sweeps) = (&profiles.geometries, &profiles.sweeps);
    let t_em = Instant::now();
    let mut fit = fit_model(surface, geometries, sweeps, &opts)?;
    let em_s = t_em.elapsed().as_secs_f64();
    let cpu_after_em = cpu_seconds();
    let (block, spacing) = (params.block, fit.stats.depth_spacing_mm);
    // The dipole baseline needs only the EM's amplitudes: it runs beside the spatial prior,
    // whose statistics and model building leave cores idle.
    let (regularised, dipole) = rayon::join(
        || -> Result<_, FitStageError> {
            let t = Instant::now();
            // Taken, so the unregularised model is freed once the filled copy exists.
            let mut model = std::mem::take(&mut fit.model);
            let prior = regularise_in_place(
                params.spatial_prior,
                &mut model,
                surface,
                geometries,
                sweeps,
                block,
                spacing,
            )?;
            let fitted = model.fitted();
            let filled = fill_unfitted(&mut model, &fitted, &surface.mask);
            let layers = model;
            Ok((prior, fitted, layers, filled, t.elapsed().as_secs_f64()))
        },
        || -> Result<_, FitStageError> {
            let t = Instant::now();
            let dipole = params
                .dipole
                .then(|| {
                    fit_dipole_model(
                        surface,
                        geometries,
                        sweeps,
                        eta,
                        params.block,
                        &fit.amplitudes,
                    )
                })
                .transpose()?;
            Ok((dipole, t.elapsed().as_secs_f64()))
        },
    );
    let (prior, fitted, layers, filled, prior_s) = regularised?;
    let (dipole, dipole_s) = dipole?;
    Ok(FittedLayers {
        layers,
        dipole,
        summary: FitSummary {
            stats: fit.stats,
            prior,
            fitted,
            filled,
            em_s,
            prior_s,
            dipole_s,
            cpu_after_em,
        },
    })
}

/// Saves the model to `path`, then draws the figures. One after the other: side by side they
/// were the run's peak at full size (1949 MiB RSS; one after the other, under 1750 MiB), and
/// both now keep every core busy on their own (the save compresses its parts side by side).
/// Returns the wall-clock seconds of each.
fn save_and_draw(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    record: &ProfilesRecord,
    model: &SubsurfaceModel,
    prepared: PreparedFigures,
    path: &Path,
) -> Result<(f64, f64), FitStageError> {
    let t = Instant::now();
    model.save(path)?;
    let save_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    write_figures(ctx, inputs, record, model, &prepared)?;
    Ok((save_s, t.elapsed().as_secs_f64()))
}

/// Frees the slits' global light of every projector: after the fit only the figures read them,
/// and [`prepare_figures`] has taken what they need.
fn release_slits(inputs: &mut ProfileInputs) {
    for p in &mut inputs.projectors {
        p.stack = SlitStack::default();
    }
}

/// Frees the projectors' images (separation, stray light; the coordinates stay, the stacked
/// sweeps are checked against their size): once
/// [`ProjectorProducts`] and Fig. 10's measured slit are taken nothing reads them (at full size
/// ~0.4 GB the EM, the prior beside the dipole, the held-out renders and the save no longer sit
/// on). The training projectors' profile geometry is moved out before; any left is dropped.
fn release_projector_images(inputs: &mut ProfileInputs) {
    for p in &mut inputs.projectors {
        p.release_white_images();
        p.geometry = GeometryMap::default();
    }
}

/// Surface pixels without layers in a channel get the homogeneous layers of that channel, in
/// place (a copy of the regularised model was the stage's peak); returns how many surface
/// pixels had none in the first channel.
fn fill_unfitted(model: &mut LayerModel, fitted: &[bool], mask: &[bool]) -> usize {
    let mean = model.mean_layers(fitted);
    let filled = (0..model.width * model.height)
        .into_par_iter()
        .filter(|&i| mask[i] && model.layers(i, 0).is_empty())
        .count();
    model.fill_empty(|i, c| mask[i].then_some(mean[c].as_slice()));
    filled
}

/// What the model file takes from the projectors' images: the direct and the white albedo (from
/// the training projectors' white frames) and every projector's visibility.
struct ProjectorProducts {
    albedo: Vec<[f32; 3]>,
    white_albedo: Vec<[f32; 3]>,
    visibility: Vec<Vec<bool>>,
}

impl ProjectorProducts {
    fn new(inputs: &ProfileInputs, training: &[usize]) -> Self {
        let surface = &inputs.surface;
        let white_irradiance: Vec<Vec<f32>> = training
            .iter()
            .map(|&k| {
                let p = &inputs.projectors[k];
                pattern_irradiance(surface, &p.view(), &Pattern::White, p.black_level, 0.0)
            })
            .collect();
        let direct: Vec<&[[f32; 3]]> = training
            .iter()
            .map(|&k| inputs.projectors[k].direct_white())
            .collect();
        let albedo = direct_albedo(&white_irradiance, &direct);
        let totals: Vec<Vec<[f32; 3]>> = training
            .iter()
            .map(|&k| {
                let p = &inputs.projectors[k];
                p.separation_direct
                    .iter()
                    .zip(&p.separation_global)
                    .map(|(d, g)| [d[0] + g[0], d[1] + g[1], d[2] + g[2]])
                    .collect()
            })
            .collect();
        let total_refs: Vec<&[[f32; 3]]> = totals.iter().map(Vec::as_slice).collect();
        let white_albedo = direct_albedo(&white_irradiance, &total_refs);
        Self {
            albedo,
            white_albedo,
            visibility: inputs
                .projectors
                .iter()
                .map(|p| p.coords.iter().map(Option::is_some).collect())
                .collect(),
        }
    }
}

/// The model file's content.
fn assemble(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    params: &FitParams,
    training: &[usize],
    (layers, dipole): (LayerModel, Option<LayerModel>),
    products: ProjectorProducts,
    stats: &mlsss_layer_model::fit::FitStats,
) -> Result<SubsurfaceModel, FitStageError> {
    let surface = &inputs.surface;
    let calibration = ctx
        .calibration
        .cloned()
        .ok_or(FitStageError::NoTrainingProjector)?;
    let ProjectorProducts {
        albedo,
        white_albedo,
        visibility,
    } = products;
    let model = SubsurfaceModel {
        header: ModelHeader {
            format_version: FORMAT_VERSION,
            width: surface.width,
            height: surface.height,
            em: params.em,
            components: params.components,
            depth_spacing_mm: stats.depth_spacing_mm,
            eta: inputs.params.eta,
            view_ray: inputs.params.view_ray,
            training_projectors: training.to_vec(),
            holdout: params.holdout,
            projectors: inputs
                .projectors
                .iter()
                .map(|p| ProjectorLight {
                    centre: p.centre.into(),
                    falloff: p.falloff,
                    black_level: p.black_level,
                    blur_px: p.blur_px,
                })
                .collect(),
            calibration,
            patterns: ctx.capture.manifest.booth.patterns.clone(),
            camera_centre: surface.camera_centre.into(),
            stats: stats.clone(),
        },
        surface: surface.clone(),
        albedo,
        white_albedo,
        visibility,
        layers,
        dipole,
    };
    Ok(model)
}

/// Relative RMS error of `a` against `t` over `mask`, all channels; `None` when the truth holds
/// no light there (a black held-out projector: every model would score 0).
pub fn rel_rmse(a: &[[f32; 3]], t: &[[f32; 3]], mask: &[bool]) -> Option<f64> {
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for ((a, t), m) in a.iter().zip(t).zip(mask) {
        if *m {
            for c in 0..3 {
                num += (f64::from(a[c]) - f64::from(t[c])).powi(2);
                den += f64::from(t[c]).powi(2);
            }
        }
    }
    (den > 0.0).then(|| (num / den).sqrt())
}

/// Held-out projector `h`: rendered global light against the simulator's, for white and the
/// slits with truth.
fn heldout_errors(
    model: &SubsurfaceModel,
    h: usize,
    truth_dir: &Path,
) -> Result<BTreeMap<String, BTreeMap<String, f64>>, FitStageError> {
    let size = (model.header.width as u32, model.header.height as u32);
    let mask: Vec<bool> = model.visibility[h]
        .iter()
        .zip(&model.surface.mask)
        .map(|(v, m)| *v && *m)
        .collect();
    let spec = &model.header.patterns;
    let slit = |axis| Pattern::Slit {
        axis,
        width: spec.slit_width_px,
        period: spec.slit_period_px,
        offset: 0,
    };
    let patterns = [Pattern::White, slit(Axis::X), slit(Axis::Y)];
    let opts = RenderOptions::default();
    // The patterns with a truth image of the model's size, and that truth.
    let mut compared = Vec::new();
    let mut truths: Vec<Vec<[f32; 3]>> = Vec::new();
    for pattern in patterns {
        let path = truth::global(truth_dir, h, &pattern);
        if !path.is_file() {
            continue;
        }
        let (width, height, pixels) = imageio::read_exr_rgb_pixels(&path)?;
        if (width, height) != size {
            continue;
        }
        truths.push(pixels);
        compared.push(pattern);
    }
    let mut out: BTreeMap<String, BTreeMap<String, f64>> = compared
        .iter()
        .map(|p| (p.label(), BTreeMap::new()))
        .collect();
    // The irradiance and shifts are found once for every renderer; every pattern of one
    // renderer is rendered in one go (its splats are found once).
    let projector = ProjectorPatterns::new(model, h, &compared)?;
    for (name, baseline) in [
        ("mlsss", Baseline::Mlsss),
        ("homogeneous", Baseline::Homogeneous),
        ("dipole", Baseline::Dipole),
    ] {
        let relits = match projector.render(baseline, &opts) {
            Ok(r) => r,
            Err(ModelFileError::NoDipole) => continue,
            Err(e) => return Err(e.into()),
        };
        for ((pattern, truth), r) in compared.iter().zip(&truths).zip(relits) {
            let error = rel_rmse(&r.global, truth, &mask).ok_or_else(|| {
                FitStageError::NothingToCompare {
                    projector: h,
                    pattern: pattern.label(),
                }
            })?;
            out.entry(pattern.label())
                .or_default()
                .insert(name.into(), error);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests;
