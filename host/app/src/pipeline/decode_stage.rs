//! Stage `decode`: Gray-code decoding of every projector (`geometry::gray_code`).
//!
//! Artefacts in `OUT/decode/`, per projector `k`:
//! - `proj{k}_coords.exr`: RGB = (u, v, valid) — sub-pixel projector column and row, and 1 where
//!   decoded (0, 0, 0 elsewhere). Same layout as the simulator's `truth/proj{k}_coords.exr`.
//! - `proj{k}_confidence.exr`: one channel, the decoder's confidence in [0, 1].
//! - `proj{k}_codes.png`: false colour, red = u, green = v (scaled to the projector size), black
//!   where not decoded.
//!
//! Report fragment: `projectors[k]` with `valid_fraction`, `flagged_fraction`, `repaired_fraction`
//! and, with ground truth, `exact_fraction`, `wrong_fraction`, `mean_abs_error_px`,
//! `missed_fraction`; plus `valid_fraction` (mean over projectors). A projector whose frames are
//! all dark is skipped and reported (`skipped`), not fatal.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use image::Rgb32FImage;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::{Stage, StageContext, StageFailure};
use mlsss_core::capture::truth;
use mlsss_core::imageio::{self, GrayF32, ImageIoError};
use mlsss_vision::geometry::code_frames::{self, CodeFramesError};
use mlsss_vision::geometry::gray_code::{
    DecodeParams, GrayCodeError, ProjectorDecode, TruthComparison, decode,
};

/// The decode stage.
pub const STAGE: Stage = Stage {
    name: "decode",
    version: 2,
    inputs: &[],
    uses_calibration: false,
    run,
};

/// Errors of the decode stage.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DecodeStageError {
    /// The frames of a projector could not be loaded.
    #[error("projector {projector}: {source}")]
    Frames {
        projector: usize,
        source: CodeFramesError,
    },
    /// The decoder rejected a projector's frames.
    #[error("projector {projector}: {source}")]
    Decode {
        projector: usize,
        source: GrayCodeError,
    },
    /// An artefact could not be written or read.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// A coordinate map has a different size than the camera.
    #[error("{path} is {width}x{height}, the camera is {camera_width}x{camera_height}")]
    Size {
        path: PathBuf,
        width: u32,
        height: u32,
        camera_width: u32,
        camera_height: u32,
    },
}

/// The decode stage's report fragment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecodeReport {
    pub projectors: Vec<ProjectorDecodeReport>,
    /// Mean of `valid_fraction` over the decoded (not skipped) projectors.
    pub valid_fraction: f64,
}

/// One projector's entry of [`DecodeReport`]: skipped (all frames dark), or its counts and, with
/// ground truth, the comparison with the true coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProjectorDecodeReport {
    pub projector: usize,
    /// Why the projector was skipped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub counts: Option<DecodeCounts>,
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<TruthComparison>,
}

/// Fractions of the camera pixels by decoding outcome.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DecodeCounts {
    pub valid_fraction: f64,
    pub flagged_fraction: f64,
    pub repaired_fraction: f64,
    pub unlit_fraction: f64,
}

/// Path of projector `k`'s coordinate map in a decode folder.
pub fn coords_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("proj{k}_coords.exr"))
}

fn run(ctx: &StageContext) -> Result<Value, StageFailure> {
    let params: DecodeParams = ctx.params()?;
    super::fragment(&run_decode(ctx, &params)?)
}

fn run_decode(ctx: &StageContext, params: &DecodeParams) -> Result<DecodeReport, StageFailure> {
    let capture = ctx.capture;
    let booth = &capture.manifest.booth;
    let truth_dir = ctx.truth_dir();
    let dir = ctx.dir();
    // Projector k's artefacts are written and compared with the truth while k + 1 decodes:
    // both are mostly serial, the decoding leaves cores idle between its parallel passes.
    let finished: Mutex<Vec<Finished>> = Mutex::new(Vec::new());
    let keep = |k: usize, entry: Result<(ProjectorDecodeReport, Option<f64>), DecodeStageError>| {
        if let Ok(mut done) = finished.lock() {
            done.push((k, entry));
        }
    };
    rayon::scope(|scope| -> Result<(), StageFailure> {
        // The previous projector's frames, read into again (no fresh page-faulted buffers).
        let mut spare = None;
        for (k, proj) in booth.projectors.iter().enumerate() {
            let frames =
                code_frames::from_capture_reusing(capture, k, spare.take()).map_err(|source| {
                    StageFailure::new(DecodeStageError::Frames {
                        projector: k,
                        source,
                    })
                })?;
            let params = camera_noise_params(params, capture, k);
            let decoded = match decode(&frames, (proj.width, proj.height), &params) {
                Ok(d) => d,
                Err(err @ (GrayCodeError::NothingLit { .. } | GrayCodeError::Saturated { .. })) => {
                    let skipped = ProjectorDecodeReport {
                        projector: k,
                        skipped: Some(err.to_string()),
                        counts: None,
                        truth: None,
                    };
                    keep(k, Ok((skipped, None)));
                    spare = Some(frames);
                    continue;
                }
                Err(source) => {
                    return Err(StageFailure::new(DecodeStageError::Decode {
                        projector: k,
                        source,
                    }));
                }
            };
            spare = Some(frames);
            let (dir, truth_dir, keep) = (&dir, &truth_dir, &keep);
            scope.spawn(move |_| keep(k, finish_projector(dir, k, &decoded, truth_dir.as_deref())));
        }
        // Freed before the last projector's artefacts are written, as before the reuse.
        drop(spare);
        Ok(())
    })?;
    let mut finished = finished
        .into_inner()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    finished.sort_by_key(|(k, _)| *k);
    let mut projectors = Vec::new();
    let mut valid_sum = 0.0;
    let mut decoded_count = 0;
    for (_, entry) in finished {
        let (entry, valid) = entry.map_err(StageFailure::new)?;
        if let Some(valid) = valid {
            valid_sum += valid;
            decoded_count += 1;
        }
        projectors.push(entry);
    }
    Ok(DecodeReport {
        projectors,
        valid_fraction: valid_sum / f64::from(decoded_count.max(1)),
    })
}

/// A projector's index and its report entry with its valid fraction (`None`: skipped).
type Finished = (
    usize,
    Result<(ProjectorDecodeReport, Option<f64>), DecodeStageError>,
);

/// Writes projector `k`'s artefacts into `dir` and makes its report entry, compared with the
/// true coordinates in `truth_dir` if given; with its valid fraction.
fn finish_projector(
    dir: &Path,
    k: usize,
    decoded: &ProjectorDecode,
    truth_dir: Option<&Path>,
) -> Result<(ProjectorDecodeReport, Option<f64>), DecodeStageError> {
    write_decode(dir, k, decoded)?;
    let truth = match truth_dir {
        Some(t) => Some(load_coords(
            &truth::projector_coords(t, k),
            (decoded.width, decoded.height),
        )?),
        None => None,
    };
    let entry = projector_report(k, decoded, truth.as_deref());
    Ok((entry, Some(decoded.summary().valid_fraction())))
}

/// The decoder's thresholds with the noise model of the capture's camera at projector `k`'s
/// exposure: each pixel's lit and bit decisions are judged against the noise this camera has at
/// that pixel's level (the `shot_noise_gain` and `read_noise` of `params` are replaced).
fn camera_noise_params(
    params: &DecodeParams,
    capture: &mlsss_core::capture::Capture,
    k: usize,
) -> DecodeParams {
    params
        .clone()
        .with_camera_noise(capture.manifest.frame_noise_of(k))
}

/// The report entry of one projector (used by the pipeline and by `mlsss decode --layout opencv`).
pub fn projector_report(
    k: usize,
    decoded: &ProjectorDecode,
    truth: Option<&[Option<(f64, f64)>]>,
) -> ProjectorDecodeReport {
    let s = decoded.summary();
    ProjectorDecodeReport {
        projector: k,
        skipped: None,
        counts: Some(DecodeCounts {
            valid_fraction: s.valid_fraction(),
            flagged_fraction: s.flagged_fraction(),
            repaired_fraction: s.repaired as f64 / s.pixels.max(1) as f64,
            unlit_fraction: s.unlit as f64 / s.pixels.max(1) as f64,
        }),
        truth: truth.map(|t| TruthComparison::new(decoded, t)),
    }
}

/// Writes projector `k`'s coordinate map, confidence and false-colour preview into `dir`.
pub fn write_decode(dir: &Path, k: usize, d: &ProjectorDecode) -> Result<(), DecodeStageError> {
    std::fs::create_dir_all(dir).map_err(|source| ImageIoError::Png {
        path: dir.to_owned(),
        source: image::ImageError::IoError(source),
    })?;
    let coords = Rgb32FImage::from_fn(d.width, d.height, |x, y| {
        let i = (y * d.width + x) as usize;
        match d.coords(i) {
            Some((u, v)) => image::Rgb([u, v, 1.0]),
            None => image::Rgb([0.0, 0.0, 0.0]),
        }
    });
    imageio::write_exr_rgb(&coords_path(dir, k), &coords)?;
    let confidence = GrayF32 {
        width: d.width,
        height: d.height,
        data: d.confidence.clone(),
    };
    imageio::write_exr_gray(&dir.join(format!("proj{k}_confidence.exr")), &confidence)?;
    let (pw, ph) = (
        d.projector_width.max(1) as f32,
        d.projector_height.max(1) as f32,
    );
    let preview = image::RgbImage::from_fn(d.width, d.height, |x, y| {
        let p = coords.get_pixel(x, y).0;
        if p[2] > 0.5 {
            let c = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
            image::Rgb([c(p[0] / pw), c(p[1] / ph), 64])
        } else {
            image::Rgb([0, 0, 0])
        }
    });
    let path = dir.join(format!("proj{k}_codes.png"));
    imageio::write_png(&path, &preview)?;
    Ok(())
}

/// Reads a coordinate map (`(u, v, valid)` EXR, ours or the simulator's truth): `Some((u, v))`
/// where valid/lit, per camera pixel, row-major.
pub fn load_coords(
    path: &Path,
    camera_size: (u32, u32),
) -> Result<Vec<Option<(f64, f64)>>, DecodeStageError> {
    let img = imageio::read_exr_rgb(path)?;
    if (img.width(), img.height()) != camera_size {
        return Err(DecodeStageError::Size {
            path: path.to_owned(),
            width: img.width(),
            height: img.height(),
            camera_width: camera_size.0,
            camera_height: camera_size.1,
        });
    }
    Ok(img
        .pixels()
        .map(|p| (p.0[2] > 0.5).then_some((p.0[0] as f64, p.0[1] as f64)))
        .collect())
}
