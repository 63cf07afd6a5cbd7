//! Leave-one-projector-out evaluation (DESIGN stage 9): relight the held-out projector from the
//! model fitted on the others, under several of its patterns, with MLSSS and every baseline, and
//! compare with what the camera recorded and (for a simulated capture) with the true subsurface
//! light.
//!
//! Conventions
//! - Reference ("real") image of pattern p: the recorded frame of the held-out projector minus
//!   the stray light of the other projectors' black level (estimated from the capture's white
//!   frames and the model's black levels, [`mlsss_vision::photometry::response::stray_light`]); the
//!   renders hold the held-out projector's light only.
//! - Compared pixels: on the subject (model mask) and lit by the held-out projector (its
//!   visibility), finite in both images. Metrics pool every compared pattern.
//! - `global_rel_rmse` compares the rendered subsurface part alone with the simulator's true
//!   global image (`truth/projK_global_<pattern>.exr`), for the patterns that have one.

use std::time::Instant;

use image::Rgb32FImage;
use serde_json::{Map, Value, json};

use super::metrics::{MetricsError, SquaredErrors};
use crate::report::figures::RelitImages;
use mlsss_core::capture::{Axis, Capture, CaptureError, Pattern, truth};
use mlsss_core::imageio::{self, ImageIoError};
use mlsss_layer_model::model_file::{Baseline, ModelFileError, SubsurfaceModel, render_projector};
use mlsss_layer_model::relight::Relit;
use mlsss_layer_model::render::RenderOptions;
use mlsss_vision::photometry::response::stray_light;

/// Errors of the held-out evaluation.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum HoldoutError {
    /// A frame of the capture could not be read.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// A truth image could not be read.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// Rendering failed.
    #[error("rendering projector {projector} ({pattern}) with {baseline:?}: {source}")]
    Render {
        projector: usize,
        pattern: String,
        baseline: Baseline,
        source: ModelFileError,
    },
    /// The metrics refused the images.
    #[error("comparing {what}: {source}")]
    Metrics { what: String, source: MetricsError },
    /// The capture and the model disagree (size, projector count).
    #[error("the capture does not match the model: {0}")]
    Mismatch(String),
    /// The capture lacks a frame the evaluation needs.
    #[error("projector {projector} has no `{pattern}` frame in the capture")]
    MissingFrame { projector: usize, pattern: String },
}

/// The renderers compared, in report order.
pub const BASELINES: [(Baseline, &str); 4] = [
    (Baseline::Mlsss, "mlsss"),
    (Baseline::Homogeneous, "homogeneous"),
    (Baseline::Dipole, "dipole"),
    (Baseline::Direct, "direct_only"),
];

/// The evaluation's result.
#[derive(Debug, Clone)]
pub struct HoldoutResult {
    /// The `relight` report object.
    pub report: Value,
    /// Seconds spent rendering.
    pub render_seconds: f64,
    /// The white and first Gray-code images, for figures.
    pub kept: Vec<RelitImages>,
    /// Compared-pixel mask.
    pub mask: Vec<bool>,
    /// The slit patterns with offset 0 that have a truth image: the truth and every renderer's
    /// global part, for the back-scatter evaluation (so it neither renders nor reads them again).
    pub slits: Vec<HeldOutSlit>,
}

/// One held-out slit pattern's true and rendered global images.
#[derive(Debug, Clone)]
pub struct HeldOutSlit {
    pub pattern: Pattern,
    pub truth: Vec<[f32; 3]>,
    /// Global part per renderer (direct-only excluded).
    pub renders: Vec<(Baseline, Vec<[f32; 3]>)>,
}

/// The held-out projector's patterns the evaluation renders: white (paper Fig. 11), a middle bit
/// of each Gray code axis (Fig. 9), the first slit of each axis and the first high-frequency
/// shift; only those the capture holds.
pub fn evaluation_patterns(capture: &Capture, k: usize) -> Vec<Pattern> {
    let plan: Vec<Pattern> = capture
        .manifest
        .plan
        .for_projector(k as u8)
        .map(|f| f.pattern)
        .collect();
    let mid_gray = |axis: Axis| {
        let bits: Vec<u32> = plan
            .iter()
            .filter_map(|p| match *p {
                Pattern::Gray {
                    axis: a,
                    bit,
                    inverted: false,
                } if a == axis => Some(bit),
                _ => None,
            })
            .collect();
        let max = bits.iter().copied().max()?;
        // A middle bit: stripes a few projector pixels wide, where subsurface blur shows.
        let bit = (max / 2).max(1).min(max);
        Some(Pattern::Gray {
            axis,
            bit,
            inverted: false,
        })
    };
    let first = |pred: &dyn Fn(&Pattern) -> bool| plan.iter().copied().find(|p| pred(p));
    [
        Some(Pattern::White),
        mid_gray(Axis::X),
        mid_gray(Axis::Y),
        first(&|p| {
            matches!(
                p,
                Pattern::Slit {
                    axis: Axis::X,
                    offset: 0,
                    ..
                }
            )
        }),
        first(&|p| {
            matches!(
                p,
                Pattern::Slit {
                    axis: Axis::Y,
                    offset: 0,
                    ..
                }
            )
        }),
        first(&|p| matches!(p, Pattern::HighFrequency { shift: 0, .. })),
    ]
    .into_iter()
    .flatten()
    .filter(|p| plan.contains(p))
    .collect()
}

fn pixels_of(img: &Rgb32FImage) -> Vec<[f32; 3]> {
    img.pixels().map(|p| p.0).collect()
}

/// Stray light under projector `k` (the other projectors' black level), from the capture's
/// white frames; zero when the black levels are unknown or the system is singular.
fn stray_under(
    capture: &Capture,
    model: &SubsurfaceModel,
    k: usize,
) -> Result<Vec<[f32; 3]>, HoldoutError> {
    let n = model.header.projectors.len();
    let blacks: Vec<f64> = model
        .header
        .projectors
        .iter()
        .map(|p| f64::from(p.black_level))
        .collect();
    let plan = &capture.manifest.plan;
    let mut whites = Vec::with_capacity(n);
    for j in 0..n {
        let spec = plan
            .find(j as u8, &Pattern::White)
            .ok_or(HoldoutError::MissingFrame {
                projector: j,
                pattern: Pattern::White.label(),
            })?;
        whites.push(capture.read_frame(spec.index)?);
    }
    let refs: Vec<&Rgb32FImage> = whites.iter().collect();
    let pixels = model.header.width * model.header.height;
    Ok(match stray_light(&refs, &blacks) {
        Some(s) => pixels_of(&s[k]),
        None => vec![[0.0; 3]; pixels],
    })
}

/// Runs the evaluation of projector `k`.
pub fn evaluate_holdout(
    capture: &Capture,
    model: &SubsurfaceModel,
    k: usize,
    renderers: &[Baseline],
    opts: &RenderOptions,
) -> Result<HoldoutResult, HoldoutError> {
    let baselines: Vec<(Baseline, &str)> = BASELINES
        .iter()
        .copied()
        .filter(|(b, _)| renderers.contains(b))
        .collect();
    let (w, h) = (model.header.width, model.header.height);
    let booth = &capture.manifest.booth;
    if (booth.camera.width as usize, booth.camera.height as usize) != (w, h) {
        return Err(HoldoutError::Mismatch(format!(
            "capture camera {}x{}, model {w}x{h}",
            booth.camera.width, booth.camera.height
        )));
    }
    let visible = model.visibility.get(k).ok_or_else(|| {
        HoldoutError::Mismatch(format!(
            "projector {k} requested, the model knows {}",
            model.visibility.len()
        ))
    })?;
    let mask: Vec<bool> = model
        .surface
        .mask
        .iter()
        .zip(visible)
        .map(|(&m, &v)| m && v)
        .collect();
    let stray = stray_under(capture, model, k)?;
    let truth_dir = capture.truth_dir();
    let patterns = evaluation_patterns(capture, k);
    let mut total = vec![SquaredErrors::default(); baselines.len()];
    let mut global = vec![SquaredErrors::default(); baselines.len()];
    let mut global_patterns = Vec::new();
    let mut per_pattern = Vec::new();
    let mut kept = Vec::new();
    let mut slits = Vec::new();
    let mut kept_gray = false;
    let mut render_seconds = 0.0;
    let metric_err = |what: String| move |source| HoldoutError::Metrics { what, source };
    for pattern in &patterns {
        let label = pattern.label();
        let spec = capture
            .manifest
            .plan
            .find(k as u8, pattern)
            .ok_or_else(|| HoldoutError::MissingFrame {
                projector: k,
                pattern: label.clone(),
            })?;
        let frame = pixels_of(&capture.read_frame(spec.index)?);
        let reference: Vec<[f32; 3]> = frame
            .iter()
            .zip(&stray)
            .map(|(f, s)| [f[0] - s[0], f[1] - s[1], f[2] - s[2]])
            .collect();
        let true_global = match &truth_dir {
            Some(t) if truth::global(t, k, pattern).is_file() => Some(pixels_of(
                &imageio::read_exr_rgb(&truth::global(t, k, pattern))?,
            )),
            _ => None,
        };
        if true_global.is_some() {
            global_patterns.push(label.clone());
        }
        let mut entry = Map::new();
        let mut renders = Vec::new();
        let keep_slit = matches!(pattern, Pattern::Slit { offset: 0, .. }) && true_global.is_some();
        let mut slit_globals = Vec::new();
        for (i, (baseline, name)) in baselines.iter().enumerate() {
            let start = Instant::now();
            let relit: Relit =
                render_projector(model, k, pattern, *baseline, opts).map_err(|source| {
                    HoldoutError::Render {
                        projector: k,
                        pattern: label.clone(),
                        baseline: *baseline,
                        source,
                    }
                })?;
            render_seconds += start.elapsed().as_secs_f64();
            let rendered = relit.total();
            let sums = SquaredErrors::accumulate(&rendered, &reference, &mask)
                .map_err(metric_err(format!("{name} under {label}")))?;
            total[i] = total[i].pooled_with(sums);
            let e = sums
                .errors()
                .map_err(metric_err(format!("{name} under {label}")))?;
            entry.insert((*name).into(), json!(e.psnr_db));
            if let (Some(tg), false) = (&true_global, *baseline == Baseline::Direct) {
                let g = SquaredErrors::accumulate(&relit.global, tg, &mask)
                    .map_err(metric_err(format!("{name} global under {label}")))?;
                global[i] = global[i].pooled_with(g);
                if keep_slit {
                    slit_globals.push((*baseline, relit.global));
                }
            }
            renders.push(((*name).to_owned(), rendered));
        }
        per_pattern.push(json!({ "pattern": label, "psnr_db": Value::Object(entry) }));
        if let (true, Some(truth)) = (keep_slit, true_global) {
            slits.push(HeldOutSlit {
                pattern: *pattern,
                truth,
                renders: slit_globals,
            });
        }
        let first_gray = matches!(pattern, Pattern::Gray { .. }) && !kept_gray;
        if matches!(pattern, Pattern::White) || first_gray {
            kept_gray |= first_gray;
            kept.push(RelitImages {
                pattern: label.clone(),
                width: w as u32,
                height: h as u32,
                reference,
                renders,
            });
        }
    }
    let mut psnr = Map::new();
    let mut rmse = Map::new();
    for (i, (_, name)) in baselines.iter().enumerate() {
        let e = total[i]
            .errors()
            .map_err(metric_err(format!("{name} over all patterns")))?;
        psnr.insert((*name).into(), json!(e.psnr_db));
        rmse.insert((*name).into(), json!(e.rmse));
    }
    let mut global_rel = Map::new();
    if !global_patterns.is_empty() {
        for (i, (b, name)) in baselines.iter().enumerate() {
            if *b == Baseline::Direct {
                continue;
            }
            let e = global[i]
                .errors()
                .map_err(metric_err(format!("{name} global")))?;
            global_rel.insert((*name).into(), json!(e.rel_rmse));
        }
    }
    let best_baseline_psnr = baselines
        .iter()
        .skip(1)
        .filter_map(|(_, n)| psnr.get(*n).and_then(Value::as_f64))
        .fold(f64::NEG_INFINITY, f64::max);
    let psnr_of = |name: &str| psnr.get(name).and_then(Value::as_f64).unwrap_or(f64::NAN);
    let mlsss_psnr = psnr_of("mlsss");
    let report = json!({
        "holdout_projector": k,
        "patterns": patterns.iter().map(Pattern::label).collect::<Vec<_>>(),
        "compared_pixels": total[0].pixels / patterns.len().max(1),
        "psnr_db": Value::Object(psnr.clone()),
        "rmse": Value::Object(rmse),
        "global_rel_rmse": if global_rel.is_empty() { Value::Null } else { Value::Object(global_rel.clone()) },
        "global_truth_patterns": global_patterns,
        "margins": {
            "psnr_db_mlsss_minus_best_baseline": mlsss_psnr - best_baseline_psnr,
            "psnr_db_mlsss_minus_homogeneous": mlsss_psnr - psnr_of("homogeneous"),
            "global_rel_rmse_homogeneous_over_mlsss": ratio(&global_rel, "homogeneous", "mlsss"),
            "global_rel_rmse_dipole_over_mlsss": ratio(&global_rel, "dipole", "mlsss"),
        },
        "per_pattern": per_pattern,
        "render_seconds": render_seconds,
    });
    Ok(HoldoutResult {
        report,
        render_seconds,
        kept,
        mask,
        slits,
    })
}

fn ratio(map: &Map<String, Value>, a: &str, b: &str) -> Value {
    match (
        map.get(a).and_then(Value::as_f64),
        map.get(b).and_then(Value::as_f64),
    ) {
        (Some(a), Some(b)) if b > 0.0 => json!(a / b),
        _ => Value::Null,
    }
}
