//! Stage `separate`: direct/global separation of every projector's high-frequency frames
//! (`photometry::separation`), after removing the dark projectors' stray black light
//! (`photometry::response::stray_light`).
//!
//! Artefacts in `OUT/separate/`:
//! - `projK_direct.exr`, `projK_global.exr`: linear RGB under projector K's full white (the frames'
//!   scale), zero where a pixel is flagged (saturated, non-finite).
//! - `projK_white.exr`: projector K's white frame without the stray light (what PS may use).
//! - `separation.png`: per projector a row of direct, global and, with ground truth, the true
//!   direct and global (same exposure), at half the camera's resolution (2x2 means).
//!
//! Report fragment: per projector counts (`projectors[k]`), the black levels used and where they
//! came from, and with ground truth `direct_rel_rmse`, `global_rel_rmse`, `total_rel_rmse`
//! (relative RMS error over the truth mask, all projectors and channels: sqrt(sum err^2 / sum
//! truth^2)).

use std::path::{Path, PathBuf};

use image::Rgb32FImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::{Stage, StageContext, StageFailure};
use mlsss_core::capture::{CaptureError, Pattern, truth};
use mlsss_core::imageio::{self, ImageIoError};
use mlsss_vision::photometry::response::stray_light;
use mlsss_vision::photometry::separation::{
    Separation, SeparationError, SeparationParams, separate,
};

/// The separation stage.
pub const STAGE: Stage = Stage {
    name: "separate",
    version: 1,
    inputs: &[],
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
}

impl Default for SeparateParams {
    fn default() -> Self {
        Self {
            blur_correction: true,
            remove_stray: true,
        }
    }
}

/// The separation stage's report fragment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeparateReport {
    pub projectors: Vec<SeparateProjectorReport>,
    /// True when the other projectors' black-level light was removed.
    pub stray_removed: bool,
    /// With ground truth: relative RMS errors (see the module documentation).
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<SeparationErrors>,
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
    /// The preview could not be written.
    #[error("{path}: {source}")]
    Preview {
        path: PathBuf,
        source: image::ImageError,
    },
}

/// Path of projector `k`'s direct image in the stage folder.
pub fn direct_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("proj{k}_direct.exr"))
}

/// Path of projector `k`'s global image in the stage folder.
pub fn global_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("proj{k}_global.exr"))
}

/// Path of projector `k`'s stray-free white image in the stage folder.
pub fn white_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("proj{k}_white.exr"))
}

fn run(ctx: &StageContext) -> Result<Value, StageFailure> {
    let params: SeparateParams = ctx.params()?;
    super::fragment(&run_separate(ctx, &params).map_err(StageFailure::new)?)
}

/// The frames of projector `k`: white and the high-frequency shifts in order.
fn projector_frames(
    ctx: &StageContext,
    k: usize,
) -> Result<(Rgb32FImage, Vec<Rgb32FImage>, u32), SeparateStageError> {
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
    let stripe = hf[0].2;
    // White first, then the shifts; decoded in parallel.
    let mut frames = std::iter::once(white.index)
        .chain(hf.iter().map(|&(_, index, _)| index))
        .collect::<Vec<_>>()
        .par_iter()
        .map(|&index| ctx.capture.read_frame(index))
        .collect::<Result<Vec<_>, _>>()?;
    let white = frames.remove(0);
    Ok((white, frames, stripe))
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
    let frames = (0..captured)
        .into_par_iter()
        .map(|k| projector_frames(ctx, k))
        .collect::<Result<Vec<_>, _>>()?;
    let whites: Vec<&Rgb32FImage> = frames.iter().map(|f| &f.0).collect();
    let stray = if params.remove_stray {
        stray_light(&whites, &black)
    } else {
        None
    };
    let dir = ctx.dir();
    let mut per_projector = Vec::new();
    let mut outputs = Vec::new();
    for (k, frames) in frames.into_iter().enumerate() {
        let offset = stray.as_ref().map(|s| &s[k]);
        let (entry, sep) = separate_projector(ctx, params, &dir, k, frames, responses[k], offset)?;
        per_projector.push(entry);
        outputs.push(sep);
    }
    let mut report = SeparateReport {
        projectors: per_projector,
        stray_removed: stray.is_some(),
        truth: None,
    };
    let truth_images = match ctx.truth_dir() {
        Some(t) if truth::direct(&t, 0, &Pattern::White).is_file() => {
            let mask = read_mask(&truth::mask(&t));
            let pairs = read_true_separation(&t, captured)?;
            report.truth = Some(relative_errors(&outputs, &pairs, mask.as_deref()));
            Some(pairs)
        }
        _ => None,
    };
    write_preview(
        &dir.join("separation.png"),
        &outputs,
        truth_images.as_deref(),
    )?;
    Ok(report)
}

/// Separates projector `k`'s high-frequency `frames` (white, shifts, stripe width) less the
/// stray light `offset`, writes its direct, global and stray-free white images to `dir`, and
/// returns its report entry with the separation. `black_level` is the calibration's, if any.
fn separate_projector(
    ctx: &StageContext,
    params: &SeparateParams,
    dir: &Path,
    k: usize,
    (white, hf, stripe): (Rgb32FImage, Vec<Rgb32FImage>, u32),
    black_level: Option<f64>,
    offset: Option<&Rgb32FImage>,
) -> Result<(SeparateProjectorReport, Separation), SeparateStageError> {
    let black = black_level.unwrap_or(0.0);
    let cleaned: Vec<Rgb32FImage> = hf.into_iter().map(|f| subtract(f, offset)).collect();
    let refs: Vec<&Rgb32FImage> = cleaned.iter().collect();
    let blur = if params.blur_correction {
        stripe_blur(ctx, k)
    } else {
        0.0
    };
    let sep_params = SeparationParams {
        black_level: black as f32,
        blur_px: blur,
        stripe_px: stripe,
        ..SeparationParams::default()
    };
    let sep = separate(&refs, &sep_params).map_err(|source| SeparateStageError::Separation {
        projector: k,
        source,
    })?;
    imageio::write_exr_rgb(&direct_path(dir, k), &sep.direct)?;
    imageio::write_exr_rgb(&global_path(dir, k), &sep.global)?;
    imageio::write_exr_rgb(&white_path(dir, k), &subtract(white, offset))?;
    let entry = SeparateProjectorReport {
        black_level: black,
        black_level_source: if black_level.is_some() {
            "calibration"
        } else {
            "none (0)"
        }
        .into(),
        blur_px: f64::from(blur),
        saturated_pixels: sep.stats.saturated_pixels,
        non_finite_pixels: sep.stats.non_finite_pixels,
        clamped_negative: sep.stats.clamped_negative,
    };
    Ok((entry, sep))
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
    outputs: &[mlsss_vision::photometry::separation::Separation],
    truth: &[(Rgb32FImage, Rgb32FImage)],
    mask: Option<&[bool]>,
) -> SeparationErrors {
    let mut acc = [0.0f64; 6];
    for (sep, (td, tg)) in outputs.iter().zip(truth) {
        if td.dimensions() != sep.direct.dimensions() {
            continue;
        }
        for (p, flag) in sep.flags.iter().enumerate() {
            if *flag != mlsss_vision::photometry::separation::SeparationFlag::Ok
                || mask.is_some_and(|m| !m.get(p).copied().unwrap_or(false))
            {
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

/// One row per projector: direct, global, [true direct, true global], scaled to the brightest
/// white of the row.
fn write_preview(
    path: &Path,
    outputs: &[mlsss_vision::photometry::separation::Separation],
    truth: Option<&[(Rgb32FImage, Rgb32FImage)]>,
) -> Result<(), SeparateStageError> {
    let Some(first) = outputs.first() else {
        return Ok(());
    };
    let (w, h) = first.direct.dimensions();
    let (tw, th) = (w.div_ceil(2), h.div_ceil(2));
    let columns = if truth.is_some() { 4 } else { 2 };
    let mut canvas = image::RgbImage::new(tw * columns, th * outputs.len() as u32);
    for (k, sep) in outputs.iter().enumerate() {
        let mut tiles = vec![&sep.direct, &sep.global];
        if let Some(t) = truth.and_then(|t| t.get(k)) {
            tiles.push(&t.0);
            tiles.push(&t.1);
        }
        let mut sums: Vec<f32> = sep
            .direct
            .iter()
            .zip(sep.global.iter())
            .map(|(a, b)| a + b)
            .collect();
        let white = if sums.is_empty() {
            1.0
        } else {
            let at = sums.len() * 99 / 100;
            *sums.select_nth_unstable_by(at, f32::total_cmp).1
        }
        .max(1e-6);
        for (col, tile) in tiles.iter().enumerate() {
            if tile.dimensions() != (w, h) {
                continue;
            }
            for (x, y) in (0..th).flat_map(|y| (0..tw).map(move |x| (x, y))) {
                let rgb = half_size_pixel(tile, x, y)
                    .map(|v| (imageio::linear_to_srgb(v / white) * 255.0).round() as u8);
                canvas.put_pixel(col as u32 * tw + x, k as u32 * th + y, image::Rgb(rgb));
            }
        }
    }
    canvas
        .save(path)
        .map_err(|source| SeparateStageError::Preview {
            path: path.to_owned(),
            source,
        })
}
