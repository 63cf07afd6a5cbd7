//! Stage `separate`: direct/global separation of every projector's high-frequency frames, after
//! removing the dark projectors' stray black light (`photometry::response::stray_light`), by one
//! of two methods ([`SeparationMethod`]):
//! - `kernel` (default, ours): the kernel-aware split of `photometry::kernel_leak`, with each
//!   pixel's kernel leak at the stripe frequency measured from the x slit sweep
//!   (`photometry::slit_leak`, `leak_reading`), the direct part then re-read by `direct_model`
//!   and averaged over `direct_smoothing_px`. The default model, the surface's specular lobe
//!   (`photometry::lobe_direct`), replaces every direct part the leak corrects, so with it the
//!   slit sweep is not read (leak 0) unless `leak_with_lobe` asks; the dichromatic fit
//!   (`photometry::dichromatic`) stands in, on the leak-corrected split, where the lobe cannot
//!   run;
//! - `nayar`: Nayar et al. 2006 with the blur correction (`photometry::separation`), the
//!   baseline.
//!
//! Artefacts in `OUT/separate/`:
//! - `projK_direct.exr`, `projK_global.exr`: linear RGB under projector K's full white (the frames'
//!   scale), zero where a pixel is flagged (saturated, non-finite).
//! - `projK_white.exr`: projector K's white frame without the stray light (what PS may use).
//! - `projK_nayar_direct.exr`: the Nayar baseline's direct image, whatever the method (what PS
//!   reads by default: `normals_stage::PsInput`).
//! - `separation.png`: per projector a row of direct, global and, with ground truth, the true
//!   direct and global (same exposure), at half the camera's resolution (2x2 means).
//!
//! Report fragment: `method`, per projector counts (`projectors[k]`: flagged pixels by reason,
//! and where the leak was read its counters and mean per channel), the black levels used and
//! where they came from, `phase_s`/`phase_cpu_s` (where the stage's time went), with the lobe
//! `lobe`, and with ground truth
//! `direct_rel_rmse`, `global_rel_rmse`, `total_rel_rmse` of the method run (relative RMS error
//! over the truth mask, all projectors and channels: sqrt(sum err^2 / sum truth^2)) and the same
//! three for the Nayar baseline under `nayar_*` (with `method: nayar` they equal the first three).

use std::path::{Path, PathBuf};

use image::Rgb32FImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::geometry_stage::{GeometryReadError, load_point_normals, load_points_file, points_path};
use super::phase_clock::{PhaseClock, PhaseTimes};
use super::projector_lights::ProjectorLights;
use super::{Stage, StageContext, StageFailure};
use mlsss_core::calibration::Calibration;
use mlsss_core::capture::{Axis, CaptureError, Pattern, truth};
use mlsss_core::imageio::{self, ImageIoError};
use mlsss_vision::photometry::dichromatic::{dichromatic_direct, set_grey_direct};
use mlsss_vision::photometry::kernel_leak::{
    LeakFlag, LeakParams, LeakSeparation, LeakStats, colourless_smoothed_direct,
    separate_with_leak, stripe_totals,
};
use mlsss_vision::photometry::lobe_direct::{
    LobeDirectParams, ProjectorView, lobe_anchored_direct, lobe_samples,
};
use mlsss_vision::photometry::response::stray_light;
use mlsss_vision::photometry::separation::{
    SeparationError, SeparationFlag, SeparationParams, separate,
};
use mlsss_vision::photometry::slit_leak::{LeakReading, SweepGeometry, leak_from_slits};
use mlsss_vision::photometry::specular_ps::SpecularParams;

/// The separation stage.
pub const STAGE: Stage = Stage {
    name: "separate",
    // 5: harmonics leak reading and dichromatic direct part by default; 6: the lobe; 7: the
    // geometry stage's point normals, no slit sweep with the lobe.
    version: 7,
    inputs: &["geometry"],
    uses_calibration: true,
    run,
};

/// Parameters of the separation stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SeparateParams {
    /// Restore the stripe contrast lost to projector defocus (`SeparationParams::blur_px`), with
    /// the defocus of the booth description and the camera footprint.
    pub blur_correction: bool,
    /// Remove the other projectors' black-level light before separating.
    pub remove_stray: bool,
    /// Which separation runs (see the module documentation).
    pub method: SeparationMethod,
    /// `kernel` method: Gaussian sigma (camera px) over which the colourless direct part is
    /// averaged (0: per pixel).
    pub direct_smoothing_px: f64,
    /// `kernel` method: how each pixel's leak is read from its slit profile.
    pub leak_reading: LeakReading,
    /// `kernel` method: how the direct part is read from the leak-corrected split.
    pub direct_model: DirectModel,
    /// `kernel` method with the lobe: also read the kernel leak from the slit sweep. The lobe
    /// replaces every direct part the leak corrects (each pixel's total and flags do not depend
    /// on it), so by default the slit frames are not read (full-size booth: 40 of the stage's
    /// 68 frames); the stripe sweep turns this on for its leak figures.
    pub leak_with_lobe: bool,
}

/// How the `kernel` method reads its direct part from the per-channel split.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DirectModel {
    /// The mean of the channels' direct parts (the reflection is colourless).
    Colourless,
    /// The colourless reflection plus the skin's body colour, read from the split's global part
    /// (`photometry::dichromatic`): the stripes cannot tell the reflection from the kernel's
    /// core, colour can.
    Dichromatic,
    /// The surface's specular lobe, from the geometry stage's points and the calibration,
    /// combined with the colour estimate (body colour per band of incidence;
    /// `photometry::lobe_direct`). Without a calibration the dichromatic part stands in.
    #[default]
    Lobe,
}

impl Default for SeparateParams {
    fn default() -> Self {
        Self {
            blur_correction: true,
            remove_stray: true,
            method: SeparationMethod::Kernel,
            // Held-out quick heads (seed 21; tuned on seed 7): sigma 1 lowers the direct error
            // of the per-pixel split by 14 % (light skin, 2.20 to 1.88) and 20 % (dark, 0.395
            // to 0.317); sigma 3 gains about 1 % more.
            direct_smoothing_px: 1.0,
            // With the dichromatic direct part the harmonics' split gives the better body colour
            // (quick heads seed 93, global/direct: type I 0.052/0.77 against 0.117/1.79 with the
            // cosine, VI 0.126/0.135 against 0.108/0.062; see the README).
            leak_reading: LeakReading::Harmonics,
            // Quick heads seed 99 (direct / global error): type I 0.80 / 0.053 with the
            // dichromatic part, 0.078 / 0.012 with the lobe; VI 0.073 / 0.134 and 0.024 / 0.066.
            direct_model: DirectModel::Lobe,
            leak_with_lobe: false,
        }
    }
}

/// The separation methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SeparationMethod {
    /// Nayar et al. 2006 with the blur correction: the baseline.
    Nayar,
    /// Kernel-aware: the global light's stripe contrast, predicted from the slit sweep, is
    /// removed from the direct part (ours).
    #[default]
    Kernel,
}

/// The separation stage's report fragment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeparateReport {
    /// The method run.
    #[serde(default)]
    pub method: SeparationMethod,
    pub projectors: Vec<SeparateProjectorReport>,
    /// True when the other projectors' black-level light was removed.
    pub stray_removed: bool,
    /// `direct_model: lobe`: the lobe's fit; absent when the dichromatic part stood in.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lobe: Option<LobeReport>,
    /// With ground truth: relative RMS errors (see the module documentation).
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<SeparationErrors>,
    /// With ground truth: the Nayar baseline's errors on the same frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nayar_direct_rel_rmse: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nayar_global_rel_rmse: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nayar_total_rel_rmse: Option<f64>,
    /// Where the stage's time went: `read` (frames and stray light), `split` (the chosen
    /// method), `nayar` (the baseline), `lobe`, `write` (images), `truth` (errors, preview).
    #[serde(flatten, default)]
    pub timing: PhaseTimes,
}

/// One projector's entry of [`SeparateReport`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeparateProjectorReport {
    pub black_level: f64,
    /// `calibration` or `none (0)`.
    pub black_level_source: String,
    /// Stripe blur restored, projector px.
    pub blur_px: f64,
    pub saturated_pixels: u64,
    pub non_finite_pixels: u64,
    pub clamped_negative: u64,
    /// The kernel leak's counters: absent with the `nayar` method, and with the lobe unless
    /// `leak_with_lobe` asked for them (the slit sweep is not read then).
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub leak: Option<LeakCounters>,
}

/// The kernel leak's counters of one projector ([`SeparateProjectorReport::leak`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LeakCounters {
    /// Pixels whose kernel is too narrow for the stripes in some channel (all their light
    /// reported global there).
    pub narrow_kernel_pixels: u64,
    /// Pixels whose slit profile is flat over the sweep (kernel wider than the slit period;
    /// leak 0).
    pub wide_kernel_pixels: u64,
    /// Pixels with no slit light (leak 0).
    pub no_profile_pixels: u64,
    /// The slits are not finer than the stripes, so the leak is the stripes' own contrast and
    /// the direct part comes out near 0 (the full-size booth).
    pub coarse_slits: bool,
    /// Mean leak per channel over the pixels with a profile.
    pub leak_mean: [f64; 3],
}

/// The specular lobe's fit (`photometry::lobe_direct`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LobeReport {
    /// The lobe's scale (specular reflectance relative to the Fresnel lobe, times the frames'
    /// exposure).
    pub sigma: f64,
    /// Body colour (chromaticity) per band of incidence cosine, grazing first, then over all
    /// pixels.
    pub body_colours: Vec<[f32; 3]>,
    /// Share of the separated pixels with a lobe (a surface point and a fitted normal).
    pub lobe_coverage: f64,
}

/// Relative RMS errors of the separation against the simulator's truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SeparationErrors {
    pub direct_rel_rmse: f64,
    pub global_rel_rmse: f64,
    pub total_rel_rmse: f64,
}

/// Errors of the separation stage.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SeparateStageError {
    /// A frame could not be read.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// An image could not be read or written.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// The separation refused its input.
    #[error("projector {projector}: {source}")]
    Separation {
        projector: usize,
        source: SeparationError,
    },
    /// The capture has no white or high-frequency frames for a projector.
    #[error("projector {0}: the capture has no white frame or no high-frequency frames")]
    MissingFrames(usize),
    /// The calibration has fewer projectors than the capture.
    #[error("the calibration has {calibrated} projectors, the capture {captured}")]
    ProjectorCount { calibrated: usize, captured: usize },
    /// The geometry stage's points or their normals could not be read or do not match the
    /// frames.
    #[error(transparent)]
    Geometry(#[from] GeometryReadError),
}

/// Path of projector `k`'s direct image in the stage folder.
pub fn direct_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("proj{k}_direct.exr"))
}

/// Path of projector `k`'s global image in the stage folder.
pub fn global_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("proj{k}_global.exr"))
}

/// Path of projector `k`'s direct image by the Nayar baseline (written whatever the method: the
/// normals stage reads it by default).
pub fn nayar_direct_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("proj{k}_nayar_direct.exr"))
}

/// Path of projector `k`'s stray-free white image in the stage folder.
pub fn white_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("proj{k}_white.exr"))
}

fn run(ctx: &StageContext) -> Result<Value, StageFailure> {
    let params: SeparateParams = ctx.params()?;
    super::fragment(&run_separate(ctx, &params).map_err(StageFailure::new)?)
}

/// One projector's frames for the separation.
struct ProjectorFrames {
    white: Rgb32FImage,
    /// The high-frequency shifts in order.
    stripes: Vec<Rgb32FImage>,
    stripe_px: u32,
    /// The x slit sweep in offset order (empty unless the `kernel` method needs it).
    slits: Vec<Rgb32FImage>,
    slit_width_px: u32,
}

/// The frames of projector `k`: white, the high-frequency shifts in order and, with
/// `with_slits`, the x slit sweep.
fn projector_frames(
    ctx: &StageContext,
    k: usize,
    with_slits: bool,
) -> Result<ProjectorFrames, SeparateStageError> {
    let plan = &ctx.capture.manifest.plan;
    let white = plan
        .find(k as u8, &Pattern::White)
        .ok_or(SeparateStageError::MissingFrames(k))?;
    let mut hf: Vec<(u32, u32, u32)> = plan
        .for_projector(k as u8)
        .filter_map(|f| match f.pattern {
            Pattern::HighFrequency { stripe, shift } => Some((shift, f.index, stripe)),
            _ => None,
        })
        .collect();
    if hf.len() < 2 {
        return Err(SeparateStageError::MissingFrames(k));
    }
    hf.sort_unstable();
    let stripe_px = hf[0].2;
    let mut slits: Vec<(u32, u32, u32)> = plan
        .for_projector(k as u8)
        .filter_map(|f| match f.pattern {
            Pattern::Slit {
                axis: Axis::X,
                width,
                offset,
                ..
            } if with_slits => Some((offset, f.index, width)),
            _ => None,
        })
        .collect();
    slits.sort_unstable();
    let slit_width_px = slits.first().map_or(0, |s| s.2);
    let indices: Vec<u32> = std::iter::once(white.index)
        .chain(hf.iter().map(|&(_, index, _)| index))
        .chain(slits.iter().map(|&(_, index, _)| index))
        .collect();
    let mut frames = indices
        .par_iter()
        .map(|&index| ctx.capture.read_frame(index))
        .collect::<Result<Vec<_>, _>>()?;
    let slit_frames = frames.split_off(1 + hf.len());
    let white = frames.remove(0);
    Ok(ProjectorFrames {
        white,
        stripes: frames,
        stripe_px,
        slits: slit_frames,
        slit_width_px,
    })
}

/// Blur of the stripes seen by a camera pixel, projector px: defocus of the booth description
/// combined with the camera footprint (a box, variance w^2 / 12), from the focal lengths and the
/// devices' distances to the world origin (the subject's nominal centre).
pub fn stripe_blur(ctx: &StageContext, k: usize) -> f32 {
    let Some(calib) = ctx.calibration else {
        return 0.0;
    };
    let (Some(spec), Some(proj)) = (
        ctx.capture.manifest.booth.projectors.get(k),
        calib.projectors.get(k),
    ) else {
        return 0.0;
    };
    let cam = &calib.camera;
    let cam_mm_per_px = cam.extrinsics.centre().coords.norm() / cam.intrinsics.fx;
    let proj_mm_per_px = proj.device.extrinsics.centre().coords.norm() / proj.device.intrinsics.fx;
    let footprint = if proj_mm_per_px > 0.0 {
        cam_mm_per_px / proj_mm_per_px
    } else {
        0.0
    };
    (spec.defocus_px.powi(2) + footprint.powi(2) / 12.0).sqrt() as f32
}

fn run_separate(
    ctx: &StageContext,
    params: &SeparateParams,
) -> Result<SeparateReport, SeparateStageError> {
    let captured = ctx.capture.manifest.booth.projectors.len();
    let calib = ctx.calibration;
    if let Some(c) = calib
        && c.projectors.len() < captured
    {
        return Err(SeparateStageError::ProjectorCount {
            calibrated: c.projectors.len(),
            captured,
        });
    }
    // Black levels from the calibration's photometric response, else 0 (reported).
    let responses: Vec<Option<f64>> = (0..captured)
        .map(|k| {
            calib
                .and_then(|c| c.projectors.get(k))
                .and_then(|p| p.response)
                .map(|r| r.black_level)
        })
        .collect();
    let black: Vec<f64> = responses.iter().map(|b| b.unwrap_or(0.0)).collect();
    let mut clock = PhaseClock::start();
    let kernel = params.method == SeparationMethod::Kernel;
    let lobe_runs = kernel && params.direct_model == DirectModel::Lobe && calib.is_some();
    let with_slits = kernel && (!lobe_runs || params.leak_with_lobe);
    let frames = (0..captured)
        .into_par_iter()
        .map(|k| projector_frames(ctx, k, with_slits))
        .collect::<Result<Vec<_>, _>>()?;
    let whites: Vec<&Rgb32FImage> = frames.iter().map(|f| &f.white).collect();
    let stray = if params.remove_stray {
        stray_light(&whites, &black)
    } else {
        None
    };
    let truth_dir = ctx
        .truth_dir()
        .filter(|t| truth::direct(t, 0, &Pattern::White).is_file());
    let dir = ctx.dir();
    let mut per_projector = Vec::new();
    let mut outputs = Vec::new();
    // The Nayar baseline of each projector (its direct part alone without truth to compare
    // with) and the cleaned whites: both written beside the lobe (each file is encoded mostly
    // on one thread, the lobe leaves cores idle), from here, not from copies.
    let mut baseline = Vec::new();
    let mut whites = Vec::new();
    for (k, frames) in frames.into_iter().enumerate() {
        let offset = stray.as_ref().map(|s| &s[k]);
        let cleaned = CleanFrames::new(frames, offset);
        clock.lap("read");
        let setup = ProjectorSetup {
            k,
            black_level: responses[k],
            blur_px: if params.blur_correction {
                stripe_blur(ctx, k)
            } else {
                0.0
            },
        };
        let (entry, split) = separate_projector(params, &setup, &cleaned, lobe_runs)?;
        clock.lap("split");
        // The baseline on the same frames: for the report's comparison and the normals stage.
        let nayar = match params.method {
            SeparationMethod::Nayar => split.clone(),
            SeparationMethod::Kernel => nayar_split(&setup, &cleaned)?,
        };
        clock.lap("nayar");
        baseline.push(if truth_dir.is_some() {
            nayar
        } else {
            Split {
                direct: nayar.direct,
                global: Rgb32FImage::default(),
                ok: Vec::new(),
                deferred: None,
            }
        });
        whites.push(cleaned.white);
        per_projector.push(entry);
        outputs.push(split);
    }
    let early: Vec<(PathBuf, &Rgb32FImage)> = baseline
        .iter()
        .zip(&whites)
        .enumerate()
        .flat_map(|(k, (nayar, white))| {
            [
                (nayar_direct_path(&dir, k), &nayar.direct),
                (white_path(&dir, k), white),
            ]
        })
        .collect();
    let (written, lobe) = rayon::join(
        || write_all(&early),
        || match calib.filter(|_| lobe_runs) {
            Some(calib) => lobe_direct_parts(ctx, calib, &mut outputs, params.direct_smoothing_px),
            None => Ok(None),
        },
    );
    written?;
    drop(early);
    drop(whites);
    if truth_dir.is_none() {
        baseline = Vec::new();
    }
    let lobe = lobe?;
    if lobe_runs && lobe.is_none() && !with_slits {
        // The lobe found no body colour: the colour rule stands in, on the leak-corrected
        // split, so the slit sweep is needed after all.
        let with_leak = SeparateParams {
            leak_with_lobe: true,
            ..params.clone()
        };
        return run_separate(ctx, &with_leak);
    }
    if lobe.is_none() {
        // No lobe (or it found no body colour): the colour rule stands in.
        for split in &mut outputs {
            split.read_deferred_direct(params.direct_model, params.direct_smoothing_px);
        }
    }
    // Phase `lobe` holds the early writes beside it, `write` the truth comparison beside the
    // writes.
    clock.lap("lobe");
    let late: Vec<(PathBuf, &Rgb32FImage)> = outputs
        .iter()
        .enumerate()
        .flat_map(|(k, split)| {
            [
                (direct_path(&dir, k), &split.direct),
                (global_path(&dir, k), &split.global),
            ]
        })
        .collect();
    let (written, compared) = rayon::join(
        || write_all(&late),
        || -> Result<_, SeparateStageError> {
            match &truth_dir {
                Some(t) => {
                    let mask = read_mask(&truth::mask(t));
                    let pairs = read_true_separation(t, captured)?;
                    let errors = relative_errors(&outputs, &pairs, mask.as_deref());
                    let nayar = relative_errors(&baseline, &pairs, mask.as_deref());
                    Ok(Some((pairs, errors, nayar)))
                }
                None => Ok(None),
            }
        },
    );
    written?;
    let compared = compared?;
    clock.lap("write");
    let mut report = SeparateReport {
        method: params.method,
        projectors: per_projector,
        stray_removed: stray.is_some(),
        lobe,
        truth: None,
        nayar_direct_rel_rmse: None,
        nayar_global_rel_rmse: None,
        nayar_total_rel_rmse: None,
        timing: PhaseTimes::default(),
    };
    let truth_images = match compared {
        Some((pairs, errors, nayar)) => {
            report.truth = Some(errors);
            report.nayar_direct_rel_rmse = Some(nayar.direct_rel_rmse);
            report.nayar_global_rel_rmse = Some(nayar.global_rel_rmse);
            report.nayar_total_rel_rmse = Some(nayar.total_rel_rmse);
            Some(pairs)
        }
        None => None,
    };
    write_preview(
        &dir.join("separation.png"),
        &outputs,
        truth_images.as_deref(),
    )?;
    clock.lap("truth");
    report.timing = clock.finish();
    Ok(report)
}

/// Writes each `(path, image)` as an EXR, the files side by side (each is encoded mostly on
/// one thread).
fn write_all<I>(files: &[(PathBuf, I)]) -> Result<(), ImageIoError>
where
    I: std::borrow::Borrow<Rgb32FImage> + Sync,
{
    files
        .par_iter()
        .try_for_each(|(path, image)| imageio::write_exr_rgb(path, image.borrow()))
}

/// A projector's frames less the stray light of the others.
struct CleanFrames {
    white: Rgb32FImage,
    stripes: Vec<Rgb32FImage>,
    stripe_px: u32,
    slits: Vec<Rgb32FImage>,
    slit_width_px: u32,
}

impl CleanFrames {
    fn new(frames: ProjectorFrames, offset: Option<&Rgb32FImage>) -> Self {
        let clean = |v: Vec<Rgb32FImage>| v.into_iter().map(|f| subtract(f, offset)).collect();
        Self {
            white: subtract(frames.white, offset),
            stripes: clean(frames.stripes),
            stripe_px: frames.stripe_px,
            slits: clean(frames.slits),
            slit_width_px: frames.slit_width_px,
        }
    }
}

/// What one projector's separation is run with.
struct ProjectorSetup {
    k: usize,
    /// The calibration's black level, if any.
    black_level: Option<f64>,
    /// Stripe blur to restore, projector px (0 without blur correction).
    blur_px: f32,
}

/// A separation's images and which pixels it separated.
#[derive(Debug, Clone)]
struct Split {
    direct: Rgb32FImage,
    global: Rgb32FImage,
    /// Per pixel: separated (not flagged).
    ok: Vec<bool>,
    /// A kernel split whose direct part is still the stripes' (the colour rule deferred until
    /// the lobe has had its chance): its flags, for [`Split::read_deferred_direct`].
    deferred: Option<Vec<LeakFlag>>,
}

impl Split {
    /// Reads a deferred kernel split's direct part by colour, as `model` says when no lobe
    /// replaced it; no-op on other splits.
    fn read_deferred_direct(&mut self, model: DirectModel, smoothing_px: f64) {
        let Some(flags) = self.deferred.take() else {
            return;
        };
        let mut sep = LeakSeparation {
            direct: std::mem::take(&mut self.direct),
            global: std::mem::take(&mut self.global),
            flags,
            stats: LeakStats::default(),
        };
        read_direct_by_colour(&mut sep, model, smoothing_px);
        (self.direct, self.global) = (sep.direct, sep.global);
    }
}

/// The direct part of a kernel split by colour: the colourless mean of the channels, or the
/// dichromatic fit (also the lobe's stand-in), which falls back to the colourless mean without
/// a body colour (no separated pixel).
fn read_direct_by_colour(sep: &mut LeakSeparation, model: DirectModel, smoothing_px: f64) {
    match model {
        DirectModel::Colourless => colourless_smoothed_direct(sep, smoothing_px),
        DirectModel::Dichromatic | DirectModel::Lobe => {
            if dichromatic_direct(sep, smoothing_px).is_none() {
                colourless_smoothed_direct(sep, smoothing_px);
            }
        }
    }
}

/// The Nayar baseline on projector `setup.k`'s frames, with its counters.
fn nayar_separation(
    setup: &ProjectorSetup,
    frames: &CleanFrames,
) -> Result<(Split, SeparateProjectorReport), SeparateStageError> {
    let black = setup.black_level.unwrap_or(0.0);
    let refs: Vec<&Rgb32FImage> = frames.stripes.iter().collect();
    let sep_params = SeparationParams {
        black_level: black as f32,
        blur_px: setup.blur_px,
        stripe_px: frames.stripe_px,
        ..SeparationParams::default()
    };
    let sep = separate(&refs, &sep_params).map_err(|source| SeparateStageError::Separation {
        projector: setup.k,
        source,
    })?;
    let mut entry = projector_entry(setup);
    entry.saturated_pixels = sep.stats.saturated_pixels;
    entry.non_finite_pixels = sep.stats.non_finite_pixels;
    entry.clamped_negative = sep.stats.clamped_negative;
    let split = Split {
        ok: sep.flags.iter().map(|f| *f == SeparationFlag::Ok).collect(),
        direct: sep.direct,
        global: sep.global,
        deferred: None,
    };
    Ok((split, entry))
}

fn nayar_split(setup: &ProjectorSetup, frames: &CleanFrames) -> Result<Split, SeparateStageError> {
    nayar_separation(setup, frames).map(|(split, _)| split)
}

/// The kernel-aware separation of projector `setup.k`'s frames, with its counters.
fn kernel_separation(
    params: &SeparateParams,
    setup: &ProjectorSetup,
    frames: &CleanFrames,
    defer_direct: bool,
) -> Result<(Split, SeparateProjectorReport), SeparateStageError> {
    let black = setup.black_level.unwrap_or(0.0) as f32;
    // Without slit frames (the lobe's default) the leak is 0: the lobe replaces the direct part
    // it would correct.
    let (leak, leak_stats) = if frames.slits.is_empty() {
        (Vec::new(), None)
    } else {
        let slit_refs: Vec<&[[f32; 3]]> = frames.slits.iter().map(rgb_pixels).collect();
        let (leak, stats) = leak_from_slits(
            &slit_refs,
            rgb_pixels(&frames.white),
            &SweepGeometry {
                slit_width_px: frames.slit_width_px,
                stripe_px: frames.stripe_px,
                black_level: black,
                blur_px: setup.blur_px,
            },
            params.leak_reading,
        );
        (leak, Some(stats))
    };
    let refs: Vec<&Rgb32FImage> = frames.stripes.iter().collect();
    let leak_params = LeakParams {
        black_level: black,
        blur_px: setup.blur_px,
        stripe_px: frames.stripe_px,
        ..LeakParams::default()
    };
    // Without the leak the stripes' harmonics only place the direct part the lobe replaces:
    // their totals and flags are all it needs.
    let split = if leak_stats.is_some() {
        separate_with_leak(&refs, &leak, &leak_params)
    } else {
        stripe_totals(&refs, &leak_params)
    };
    let mut sep = split.map_err(|source| SeparateStageError::Separation {
        projector: setup.k,
        source,
    })?;
    // The lobe replaces the colour rule's direct part once every projector is split
    // (`lobe_direct_parts`), so the rule waits for the lobe, which needs a calibration.
    if !defer_direct {
        read_direct_by_colour(&mut sep, params.direct_model, params.direct_smoothing_px);
    }
    let mut entry = projector_entry(setup);
    entry.saturated_pixels = sep.stats.saturated_pixels;
    entry.non_finite_pixels = sep.stats.non_finite_pixels;
    entry.clamped_negative = sep.stats.clamped;
    entry.leak = leak_stats.map(|stats| LeakCounters {
        narrow_kernel_pixels: sep.stats.narrow_kernel_pixels,
        wide_kernel_pixels: stats.wide_kernel_pixels,
        no_profile_pixels: stats.no_profile_pixels,
        coarse_slits: stats.coarse_slits,
        leak_mean: mean_leak(&leak, &sep.flags),
    });
    // Every pixel with an output counts in the errors: a pixel flagged for a narrow kernel
    // carries its light as global (or, with the dichromatic direct part, split by colour), and
    // leaving them out hid a quarter of a dark head (type VI, seed 97: global 0.30 over the rest,
    // 1.02 over all pixels, with the cosine reading and the colourless direct part).
    let split = Split {
        ok: sep
            .flags
            .iter()
            .map(|f| matches!(f, LeakFlag::Ok | LeakFlag::NarrowKernel))
            .collect(),
        direct: sep.direct,
        global: sep.global,
        deferred: defer_direct.then_some(sep.flags),
    };
    Ok((split, entry))
}

/// Replaces the direct part of every split by the lobe-anchored one (`photometry::lobe_direct`),
/// with the lobes from the geometry stage's points and `calib`'s projectors; `None` (the splits
/// unchanged) when no body colour can be read.
fn lobe_direct_parts(
    ctx: &StageContext,
    calib: &Calibration,
    splits: &mut [Split],
    smoothing_px: f64,
) -> Result<Option<LobeReport>, SeparateStageError> {
    let Some((width, height)) = splits.first().map(|s| s.direct.dimensions()) else {
        return Ok(None);
    };
    let geometry = ctx.stage_dir("geometry");
    let points = load_points_file(&points_path(&geometry), (width, height))?;
    let lights = ProjectorLights::from_calibration(calib, splits.len(), width, &points);
    let normals = load_point_normals(&geometry, (width, height))?;
    // Every fitted normal, reliable or not: where the window leaves the image or the head the
    // plane is fitted to fewer points but still follows the surface, and the colour estimate
    // that stands in without a lobe is poor on light skin (virtual booth, quick type I head,
    // seed 99: direct error 0.30 with only the reliable normals, nearly all of it in the
    // columns where the head leaves the frame).
    let specular = SpecularParams::default();
    let lobes = lobe_samples(
        &lights,
        &normals.normals,
        width,
        specular.transmission.eta,
        specular.roughness,
    );
    // The lobe model knows no occlusion. Taking it away where projector k's code did not
    // decode (cast shadows, but also dim pixels the decoder missed) changed little on the
    // virtual booth's heads (seed 99, direct error: type I 0.082 -> 0.078, VI 0.022 -> 0.024),
    // which have few cast shadows; a face with deep ones may need it.
    let totals: Vec<Vec<[f32; 3]>> = splits
        .iter()
        .map(|s| {
            s.direct
                .as_raw()
                .par_chunks_exact(3)
                .zip(s.global.as_raw().par_chunks_exact(3))
                .map(|(d, g)| std::array::from_fn(|c| d[c] + g[c]))
                .collect()
        })
        .collect();
    let views: Vec<ProjectorView> = splits
        .iter()
        .zip(&totals)
        .zip(&lobes)
        .map(|((split, totals), lobes)| ProjectorView {
            totals,
            lobes,
            usable: &split.ok,
        })
        .collect();
    let Some(fit) = lobe_anchored_direct(&views, &LobeDirectParams::default()) else {
        return Ok(None);
    };
    let (mut with_lobe, mut usable) = (0usize, 0usize);
    for (split, lobes) in splits.iter().zip(&lobes) {
        for (ok, lobe) in split.ok.iter().zip(lobes) {
            usable += usize::from(*ok);
            with_lobe += usize::from(*ok && lobe.is_some());
        }
    }
    for (split, direct) in splits.iter_mut().zip(fit.direct) {
        set_grey_direct(
            &mut split.direct,
            &mut split.global,
            direct,
            &split.ok,
            smoothing_px,
        );
    }
    Ok(Some(LobeReport {
        sigma: fit.sigma,
        body_colours: fit.body_colours,
        lobe_coverage: if usable > 0 {
            with_lobe as f64 / usable as f64
        } else {
            0.0
        },
    }))
}

/// Mean leak per channel over the separated pixels.
fn mean_leak(leak: &[[f32; 3]], flags: &[LeakFlag]) -> [f64; 3] {
    let mut sum = [0.0f64; 3];
    let mut count = 0usize;
    for (l, _) in leak
        .iter()
        .zip(flags)
        .filter(|(l, f)| **f == LeakFlag::Ok && l.iter().any(|v| *v > 0.0))
    {
        (0..3).for_each(|c| sum[c] += f64::from(l[c]));
        count += 1;
    }
    sum.map(|s| if count > 0 { s / count as f64 } else { 0.0 })
}

/// `img`'s pixels as RGB triples, without a copy (the slit sweep alone is 40 full-size frames).
fn rgb_pixels(img: &Rgb32FImage) -> &[[f32; 3]] {
    // An RGB buffer holds 3 values per pixel, so nothing is left over.
    img.as_raw().as_chunks::<3>().0
}

/// A report entry with the setup filled in and every counter at 0.
fn projector_entry(setup: &ProjectorSetup) -> SeparateProjectorReport {
    SeparateProjectorReport {
        black_level: setup.black_level.unwrap_or(0.0),
        black_level_source: if setup.black_level.is_some() {
            "calibration"
        } else {
            "none (0)"
        }
        .into(),
        blur_px: f64::from(setup.blur_px),
        saturated_pixels: 0,
        non_finite_pixels: 0,
        clamped_negative: 0,
        leak: None,
    }
}

/// Separates projector `setup.k`'s stray-free frames by `params.method`; returns its report
/// entry and the split.
fn separate_projector(
    params: &SeparateParams,
    setup: &ProjectorSetup,
    frames: &CleanFrames,
    defer_direct: bool,
) -> Result<(SeparateProjectorReport, Split), SeparateStageError> {
    let (split, entry) = match params.method {
        SeparationMethod::Nayar => nayar_separation(setup, frames)?,
        SeparationMethod::Kernel => kernel_separation(params, setup, frames, defer_direct)?,
    };
    Ok((entry, split))
}

/// The simulator's true direct and global images under each projector's white, from
/// `truth_dir`.
fn read_true_separation(
    truth_dir: &Path,
    captured: usize,
) -> Result<Vec<(Rgb32FImage, Rgb32FImage)>, SeparateStageError> {
    (0..captured)
        .into_par_iter()
        .map(|k| {
            Ok((
                imageio::read_exr_rgb(&truth::direct(truth_dir, k, &Pattern::White))?,
                imageio::read_exr_rgb(&truth::global(truth_dir, k, &Pattern::White))?,
            ))
        })
        .collect::<Result<Vec<_>, SeparateStageError>>()
}

/// `frame` less the stray light `offset`, clamped at 0 (in place: each frame is used once).
fn subtract(mut frame: Rgb32FImage, offset: Option<&Rgb32FImage>) -> Rgb32FImage {
    if let Some(o) = offset {
        for (v, s) in frame.iter_mut().zip(o.iter()) {
            *v = (*v - s).max(0.0);
        }
    }
    frame
}

/// The truth mask (non-zero = subject), if readable.
fn read_mask(path: &Path) -> Option<Vec<bool>> {
    let img = image::open(path).ok()?.to_luma8();
    Some(img.into_raw().into_iter().map(|v| v > 0).collect())
}

/// Relative RMS errors of direct, global and their sum over the mask (saturated pixels, which the
/// separation flags, are left out).
fn relative_errors(
    outputs: &[Split],
    truth: &[(Rgb32FImage, Rgb32FImage)],
    mask: Option<&[bool]>,
) -> SeparationErrors {
    let mut acc = [0.0f64; 6];
    for (sep, (td, tg)) in outputs.iter().zip(truth) {
        if td.dimensions() != sep.direct.dimensions() {
            continue;
        }
        for (p, ok) in sep.ok.iter().enumerate() {
            if !ok || mask.is_some_and(|m| !m.get(p).copied().unwrap_or(false)) {
                continue;
            }
            for c in 0..3 {
                let i = p * 3 + c;
                let (d, g) = (sep.direct.as_raw()[i] as f64, sep.global.as_raw()[i] as f64);
                let (dt, gt) = (td.as_raw()[i] as f64, tg.as_raw()[i] as f64);
                acc[0] += (d - dt).powi(2);
                acc[1] += dt * dt;
                acc[2] += (g - gt).powi(2);
                acc[3] += gt * gt;
                acc[4] += (d + g - dt - gt).powi(2);
                acc[5] += (dt + gt).powi(2);
            }
        }
    }
    let ratio = |e: f64, t: f64| if t > 0.0 { (e / t).sqrt() } else { 0.0 };
    SeparationErrors {
        direct_rel_rmse: ratio(acc[0], acc[1]),
        global_rel_rmse: ratio(acc[2], acc[3]),
        total_rel_rmse: ratio(acc[4], acc[5]),
    }
}

/// Pixel `(x, y)` of `img` at half resolution: the mean of its 2x2 block (of the pixels inside).
fn half_size_pixel(img: &Rgb32FImage, x: u32, y: u32) -> [f32; 3] {
    let (w, h) = img.dimensions();
    let mut sum = [0.0f32; 3];
    let mut count = 0.0f32;
    for (px, py) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let (sx, sy) = (2 * x + px, 2 * y + py);
        if sx < w && sy < h {
            let p = img.get_pixel(sx, sy).0;
            (0..3).for_each(|c| sum[c] += p[c]);
            count += 1.0;
        }
    }
    sum.map(|v| v / count.max(1.0))
}

/// The white of a projector's preview row: the 99th percentile of its direct + global (at least
/// 1e-6; 1 for an empty image).
fn preview_white(sep: &Split) -> f32 {
    let mut sums: Vec<f32> = sep
        .direct
        .iter()
        .zip(sep.global.iter())
        .map(|(a, b)| a + b)
        .collect();
    if sums.is_empty() {
        return 1.0;
    }
    let at = sums.len() * 99 / 100;
    sums.select_nth_unstable_by(at, f32::total_cmp).1.max(1e-6)
}

/// One row per projector: direct, global, [true direct, true global], scaled to the brightest
/// white of the row. The canvas rows are drawn on every core (the same bytes as one after
/// another): drawn on one, they were the separate stage's last serial stretch (~0.15 s at full
/// size, perf).
fn write_preview(
    path: &Path,
    outputs: &[Split],
    truth: Option<&[(Rgb32FImage, Rgb32FImage)]>,
) -> Result<(), SeparateStageError> {
    let Some(first) = outputs.first() else {
        return Ok(());
    };
    let (w, h) = first.direct.dimensions();
    let (tw, th) = (w.div_ceil(2), h.div_ceil(2));
    let columns = if truth.is_some() { 4 } else { 2 };
    let whites: Vec<f32> = outputs.par_iter().map(preview_white).collect();
    // At least one byte a row: an empty image draws nothing either way.
    let row_bytes = ((tw * columns) as usize * 3).max(1);
    let mut canvas = image::RgbImage::new(tw * columns, th * outputs.len() as u32);
    canvas
        .par_chunks_exact_mut(row_bytes)
        .enumerate()
        .for_each(|(row, bytes)| {
            let (k, y) = (row / th as usize, (row % th as usize) as u32);
            let sep = &outputs[k];
            let true_pair = truth.and_then(|t| t.get(k));
            let tiles = [Some(&sep.direct), Some(&sep.global)]
                .into_iter()
                .chain([true_pair.map(|t| &t.0), true_pair.map(|t| &t.1)]);
            for (col, tile) in tiles.enumerate() {
                let Some(tile) = tile.filter(|t| t.dimensions() == (w, h)) else {
                    continue;
                };
                let start = col * tw as usize * 3;
                for (x, rgb) in (0..tw).zip(bytes[start..].chunks_exact_mut(3)) {
                    let pixel = half_size_pixel(tile, x, y);
                    for (byte, v) in rgb.iter_mut().zip(pixel) {
                        *byte = imageio::srgb_byte(v / whites[k]);
                    }
                }
            }
        });
    // Atomic: a reader (the HTML report, a viewer) never sees a half-written preview.
    Ok(imageio::write_png(path, &canvas)?)
}
