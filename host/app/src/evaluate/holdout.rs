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

use std::collections::BTreeMap;
use std::time::Instant;

use image::Rgb32FImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::metrics::{MetricsError, SquaredErrors};
use crate::report::figures::RelitImages;
use mlsss_core::capture::{Axis, Capture, CaptureError, Pattern, truth};
use mlsss_core::imageio::{self, ImageIoError};
use mlsss_layer_model::model_file::{Baseline, ModelFileError, ProjectorPatterns, SubsurfaceModel};
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
    /// The held-out projector's light could not be prepared (before any renderer ran).
    #[error("lighting the model with projector {projector}: {source}")]
    Lighting {
        projector: usize,
        source: ModelFileError,
    },
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
    /// The held-out projector's recorded frames cannot serve as a reference: black (nothing to
    /// compare with, every model would score the same) or saturated (the truth is clipped).
    #[error(
        "projector {projector}'s recorded white frame is {what} where the model sees it: \
         {detail}; the comparison would be meaningless. Check the capture (projector off, \
         exposure)"
    )]
    UnusableReference {
        projector: usize,
        what: &'static str,
        detail: String,
    },
}

/// A white reference whose mean under the mask is below this (linear, 1 = saturation) is black:
/// lit skin is at 0.05-0.8.
const BLACK_REFERENCE_MEAN: f64 = 2e-3;
/// A linear value at or above this is saturated.
const SATURATED_VALUE: f32 = 0.995;
/// A white reference with more than this share of saturated pixels under the mask is
/// overexposed (a specular highlight covers a few percent).
const MAX_SATURATED_SHARE: f64 = 0.2;

/// Refuses a black or overexposed white frame of projector `k` (`frame`, as recorded) as the
/// evaluation's reference.
fn check_reference(frame: &[[f32; 3]], k: usize, mask: &[bool]) -> Result<(), HoldoutError> {
    let compared: Vec<&[f32; 3]> = frame
        .iter()
        .zip(mask)
        .filter_map(|(p, &m)| m.then_some(p))
        .collect();
    let unusable = |what, detail| HoldoutError::UnusableReference {
        projector: k,
        what,
        detail,
    };
    if compared.is_empty() {
        return Err(unusable(
            "not seen",
            "the model has no pixel lit by this projector".into(),
        ));
    }
    let n = compared.len() as f64;
    let mean = compared
        .iter()
        .map(|p| f64::from(p[0] + p[1] + p[2]) / 3.0)
        .sum::<f64>()
        / n;
    if mean < BLACK_REFERENCE_MEAN {
        return Err(unusable(
            "black",
            format!("mean level {mean:.5} over {} pixels", compared.len()),
        ));
    }
    let saturated = compared
        .iter()
        .filter(|p| p.iter().any(|&v| v >= SATURATED_VALUE))
        .count() as f64
        / n;
    if saturated > MAX_SATURATED_SHARE {
        return Err(unusable(
            "saturated",
            format!("{:.0} % of its pixels are at full scale", 100.0 * saturated),
        ));
    }
    Ok(())
}

/// The renderers compared, in report order.
pub const BASELINES: [(Baseline, &str); 4] = [
    (Baseline::Mlsss, "mlsss"),
    (Baseline::Homogeneous, "homogeneous"),
    (Baseline::Dipole, "dipole"),
    (Baseline::Direct, "direct_only"),
];

/// The `relight` report object: the held-out projector's renders against the recorded frames
/// and the truth. Per-renderer maps are keyed by the names of [`BASELINES`].
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RelightReport {
    pub holdout_projector: usize,
    /// Labels of the evaluated patterns.
    pub patterns: Vec<String>,
    /// Compared pixels per pattern.
    pub compared_pixels: usize,
    /// Pooled over the patterns: PSNR (dB, peak 1.0) and RMSE of the total render.
    pub psnr_db: BTreeMap<String, f64>,
    pub rmse: BTreeMap<String, f64>,
    /// Relative RMS error of the rendered subsurface light against the simulator's, over the
    /// patterns with a truth image (null without any).
    pub global_rel_rmse: Option<BTreeMap<String, f64>>,
    pub global_truth_patterns: Vec<String>,
    pub margins: Margins,
    pub per_pattern: Vec<PatternPsnr>,
    pub render_seconds: f64,
    /// The back-scatter split (`evaluate::backscatter`), added for simulated captures.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub backscatter: Option<super::backscatter::BackscatterReport>,
}

impl RelightReport {
    /// A renderer's pooled PSNR, dB.
    pub fn psnr(&self, renderer: &str) -> Option<f64> {
        self.psnr_db.get(renderer).copied()
    }

    /// A renderer's pooled RMSE.
    pub fn rmse_of(&self, renderer: &str) -> Option<f64> {
        self.rmse.get(renderer).copied()
    }

    /// A renderer's global relative RMSE.
    pub fn global_rel_rmse_of(&self, renderer: &str) -> Option<f64> {
        self.global_rel_rmse.as_ref()?.get(renderer).copied()
    }
}

/// How MLSSS compares with the baselines.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Margins {
    pub psnr_db_mlsss_minus_best_baseline: f64,
    pub psnr_db_mlsss_minus_homogeneous: f64,
    pub global_rel_rmse_homogeneous_over_mlsss: Option<f64>,
    pub global_rel_rmse_dipole_over_mlsss: Option<f64>,
}

/// Per pattern: each renderer's PSNR, dB.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PatternPsnr {
    pub pattern: String,
    pub psnr_db: BTreeMap<String, f64>,
}

/// The evaluation's result.
#[derive(Debug, Clone)]
pub struct HoldoutResult {
    /// The `relight` report object.
    pub report: RelightReport,
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
/// white frames (`whites[j]`: projector `j`'s); zero when the black levels are unknown or the
/// system is singular.
fn stray_under(
    whites: &[Rgb32FImage],
    model: &SubsurfaceModel,
    k: usize,
) -> Result<Vec<[f32; 3]>, HoldoutError> {
    let n = model.header.projectors.len();
    if whites.len() != n {
        return Err(HoldoutError::Mismatch(format!(
            "the capture has {} projectors, the model {n}",
            whites.len()
        )));
    }
    let blacks: Vec<f64> = model
        .header
        .projectors
        .iter()
        .map(|p| f64::from(p.black_level))
        .collect();
    let refs: Vec<&Rgb32FImage> = whites.iter().collect();
    let pixels = model.header.width * model.header.height;
    Ok(match stray_light(&refs, &blacks) {
        Some(s) => pixels_of(&s[k]),
        None => vec![[0.0; 3]; pixels],
    })
}

/// What the evaluation of projector `k` reads from the capture, none of it depending on the
/// model: every projector's white frame (for the stray light), and the held-out projector's
/// recorded frame and (simulated captures) true global image under each evaluated pattern.
/// Why apart from the evaluation: the images are read in parallel, and a caller can load the
/// model beside them (one core inflates the quick demo's model for about 0.3 s).
pub struct HeldOutImages {
    projector: usize,
    patterns: Vec<Pattern>,
    whites: Vec<Rgb32FImage>,
    /// Per pattern: the recorded frame and the true global image, if any.
    recorded: Vec<RecordedPattern>,
}

/// The recorded frame of one pattern and the simulator's true global image of it, if any.
struct RecordedPattern {
    frame: Vec<[f32; 3]>,
    true_global: Option<Vec<[f32; 3]>>,
}

impl HeldOutImages {
    /// Reads the images of projector `k`'s evaluation ([`evaluation_patterns`]).
    pub fn read(capture: &Capture, k: usize) -> Result<Self, HoldoutError> {
        let plan = &capture.manifest.plan;
        let white_frames = (0..capture.manifest.booth.projectors.len())
            .map(|j| {
                plan.find(j as u8, &Pattern::White)
                    .map(|spec| spec.index)
                    .ok_or(HoldoutError::MissingFrame {
                        projector: j,
                        pattern: Pattern::White.label(),
                    })
            })
            .collect::<Result<Vec<u32>, _>>()?;
        let patterns = evaluation_patterns(capture, k);
        let (whites, recorded) = rayon::join(
            || {
                white_frames
                    .par_iter()
                    .map(|&index| Ok(capture.read_frame(index)?))
                    .collect::<Result<Vec<_>, HoldoutError>>()
            },
            || {
                patterns
                    .par_iter()
                    .map(|pattern| recorded_and_truth(capture, k, pattern))
                    .collect::<Result<Vec<_>, HoldoutError>>()
            },
        );
        Ok(Self {
            projector: k,
            patterns,
            whites: whites?,
            recorded: recorded?,
        })
    }
}

/// The recorded frame of projector `k` under `pattern` and the simulator's true global image
/// of it, when the capture has one.
fn recorded_and_truth(
    capture: &Capture,
    k: usize,
    pattern: &Pattern,
) -> Result<RecordedPattern, HoldoutError> {
    let spec = capture
        .manifest
        .plan
        .find(k as u8, pattern)
        .ok_or_else(|| HoldoutError::MissingFrame {
            projector: k,
            pattern: pattern.label(),
        })?;
    let frame = pixels_of(&capture.read_frame(spec.index)?);
    let true_global = match capture.truth_dir() {
        Some(t) if truth::global(&t, k, pattern).is_file() => {
            Some(imageio::read_exr_rgb_pixels(&truth::global(&t, k, pattern))?.2)
        }
        _ => None,
    };
    Ok(RecordedPattern { frame, true_global })
}

/// Runs the evaluation of projector `k`.
pub fn evaluate_holdout(
    capture: &Capture,
    model: &SubsurfaceModel,
    k: usize,
    renderers: &[Baseline],
    opts: &RenderOptions,
) -> Result<HoldoutResult, HoldoutError> {
    let images = HeldOutImages::read(capture, k)?;
    evaluate_read_holdout(capture, images, model, renderers, opts)
}

/// Runs the evaluation of the projector whose capture images `images` holds.
pub fn evaluate_read_holdout(
    capture: &Capture,
    images: HeldOutImages,
    model: &SubsurfaceModel,
    renderers: &[Baseline],
    opts: &RenderOptions,
) -> Result<HoldoutResult, HoldoutError> {
    let k = images.projector;
    let baselines: Vec<(Baseline, &str)> = BASELINES
        .iter()
        .copied()
        .filter(|(b, _)| renderers.contains(b))
        .collect();
    let mask = compared_mask(capture, model, k)?;
    let HeldOutImages {
        patterns,
        whites,
        recorded,
        ..
    } = images;
    if let Some(i) = patterns.iter().position(|p| *p == Pattern::White) {
        check_reference(&recorded[i].frame, k, &mask)?;
    }
    let stray = stray_under(&whites, model, k)?;
    drop(whites);
    let mut pooled = Pooled::new(baselines.len());
    let mut per_pattern = Vec::new();
    let mut kept = Vec::new();
    let mut slits = Vec::new();
    // (Recorded frame less the stray light, true global image), per pattern.
    let references: Vec<_> = recorded
        .into_iter()
        .map(|r| (less_stray(&r.frame, &stray), r.true_global))
        .collect();
    // The figures show the white and the first Gray-code pattern: only their renders are kept.
    let first_gray = patterns
        .iter()
        .position(|p| matches!(p, Pattern::Gray { .. }));
    let shown: Vec<bool> = (0..patterns.len())
        .map(|i| matches!(patterns[i], Pattern::White) || Some(i) == first_gray)
        .collect();
    let scenes: Vec<PatternScene> = patterns
        .iter()
        .zip(&references)
        .map(|(pattern, (reference, true_global))| PatternScene {
            pattern,
            reference,
            true_global: true_global.as_deref(),
            mask: &mask,
        })
        .collect();
    let mut evaluations: Vec<PatternEvaluation> =
        scenes.iter().map(PatternScene::new_evaluation).collect();
    // The patterns' irradiance and the light's shifts are the same for every renderer: found
    // once (they were found again for each: 7 % of the quick demo evaluation's CPU), their time
    // shared among the renderers.
    let start = Instant::now();
    let lit =
        ProjectorPatterns::new(model, k, &patterns).map_err(|source| HoldoutError::Lighting {
            projector: k,
            source,
        })?;
    let lighting_seconds = start.elapsed().as_secs_f64() / baselines.len().max(1) as f64;
    // Every pattern of one renderer is rendered in one go (the splats are found once).
    for (baseline, name) in &baselines {
        let start = Instant::now();
        let relits = lit
            .render(*baseline, opts)
            .map_err(|source| HoldoutError::Render {
                projector: k,
                pattern: patterns
                    .iter()
                    .map(Pattern::label)
                    .collect::<Vec<_>>()
                    .join(","),
                baseline: *baseline,
                source,
            })?;
        let seconds =
            (lighting_seconds + start.elapsed().as_secs_f64()) / patterns.len().max(1) as f64;
        for (((scene, e), relit), &show) in
            scenes.iter().zip(&mut evaluations).zip(relits).zip(&shown)
        {
            e.render_seconds += seconds;
            scene.add(e, *baseline, name, relit, show)?;
        }
    }
    for ((pattern, e), (reference, true_global)) in patterns.iter().zip(evaluations).zip(references)
    {
        pooled.add(&e, true_global.is_some(), pattern.label());
        per_pattern.push(PatternPsnr {
            pattern: pattern.label(),
            psnr_db: e.psnr_db,
        });
        if let (true, Some(truth)) = (e.keep_slit, true_global) {
            slits.push(HeldOutSlit {
                pattern: *pattern,
                truth,
                renders: e.slit_globals,
            });
        }
        if !e.renders.is_empty() {
            kept.push(RelitImages {
                pattern: pattern.label(),
                width: model.header.width as u32,
                height: model.header.height as u32,
                reference,
                renders: e.renders,
            });
        }
    }
    let report = pooled.report(k, &patterns, &baselines, per_pattern)?;
    Ok(HoldoutResult {
        render_seconds: report.render_seconds,
        report,
        kept,
        mask,
        slits,
    })
}

/// The compared pixels: on the subject and lit by projector `k`; checks that the capture and
/// the model agree.
fn compared_mask(
    capture: &Capture,
    model: &SubsurfaceModel,
    k: usize,
) -> Result<Vec<bool>, HoldoutError> {
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
    Ok(model
        .surface
        .mask
        .iter()
        .zip(visible)
        .map(|(&m, &v)| m && v)
        .collect())
}

/// A recorded frame less the stray light.
fn less_stray(frame: &[[f32; 3]], stray: &[[f32; 3]]) -> Vec<[f32; 3]> {
    frame
        .iter()
        .zip(stray)
        .map(|(f, s)| [f[0] - s[0], f[1] - s[1], f[2] - s[2]])
        .collect()
}

/// What one pattern of the held-out projector is compared with.
struct PatternScene<'a> {
    pattern: &'a Pattern,
    reference: &'a [[f32; 3]],
    true_global: Option<&'a [[f32; 3]]>,
    mask: &'a [bool],
}

/// One pattern's renders and error sums, per renderer (in the order of the baselines).
struct PatternEvaluation {
    psnr_db: BTreeMap<String, f64>,
    total: Vec<SquaredErrors>,
    /// Subsurface part against the truth (default sums for direct-only or without truth).
    global: Vec<SquaredErrors>,
    renders: Vec<(String, Vec<[f32; 3]>)>,
    /// A slit with offset 0 and a truth image: its global parts are kept for the back-scatter.
    keep_slit: bool,
    slit_globals: Vec<(Baseline, Vec<[f32; 3]>)>,
    render_seconds: f64,
}

fn metric_err(what: String) -> impl FnOnce(MetricsError) -> HoldoutError {
    move |source| HoldoutError::Metrics { what, source }
}

impl PatternScene<'_> {
    /// An evaluation with no renderer yet.
    fn new_evaluation(&self) -> PatternEvaluation {
        PatternEvaluation {
            psnr_db: BTreeMap::new(),
            total: Vec::new(),
            global: Vec::new(),
            renders: Vec::new(),
            keep_slit: matches!(self.pattern, Pattern::Slit { offset: 0, .. })
                && self.true_global.is_some(),
            slit_globals: Vec::new(),
            render_seconds: 0.0,
        }
    }

    /// Compares one renderer's render of the pattern (renderers are added in the order of the
    /// baselines); keeps the render when `show`.
    fn add(
        &self,
        e: &mut PatternEvaluation,
        baseline: Baseline,
        name: &str,
        relit: Relit,
        show: bool,
    ) -> Result<(), HoldoutError> {
        let label = self.pattern.label();
        let rendered = relit.total();
        let sums = SquaredErrors::accumulate(&rendered, self.reference, self.mask)
            .map_err(metric_err(format!("{name} under {label}")))?;
        e.total.push(sums);
        let errors = sums
            .errors()
            .map_err(metric_err(format!("{name} under {label}")))?;
        e.psnr_db.insert(name.into(), errors.psnr_db);
        let mut global = SquaredErrors::default();
        if let (Some(tg), false) = (self.true_global, baseline == Baseline::Direct) {
            global = SquaredErrors::accumulate(&relit.global, tg, self.mask)
                .map_err(metric_err(format!("{name} global under {label}")))?;
            if e.keep_slit {
                e.slit_globals.push((baseline, relit.global));
            }
        }
        e.global.push(global);
        if show {
            e.renders.push((name.to_owned(), rendered));
        }
        Ok(())
    }
}

/// Error sums pooled over the patterns, per renderer.
struct Pooled {
    total: Vec<SquaredErrors>,
    global: Vec<SquaredErrors>,
    global_patterns: Vec<String>,
    render_seconds: f64,
}

impl Pooled {
    fn new(renderers: usize) -> Self {
        Self {
            total: vec![SquaredErrors::default(); renderers],
            global: vec![SquaredErrors::default(); renderers],
            global_patterns: Vec::new(),
            render_seconds: 0.0,
        }
    }

    fn add(&mut self, e: &PatternEvaluation, has_truth: bool, label: String) {
        for (acc, sums) in self.total.iter_mut().zip(&e.total) {
            *acc = acc.pooled_with(*sums);
        }
        if has_truth {
            for (acc, sums) in self.global.iter_mut().zip(&e.global) {
                *acc = acc.pooled_with(*sums);
            }
            self.global_patterns.push(label);
        }
        self.render_seconds += e.render_seconds;
    }

    /// The report: pooled metrics per renderer and MLSSS's margins over the baselines.
    fn report(
        self,
        k: usize,
        patterns: &[Pattern],
        baselines: &[(Baseline, &str)],
        per_pattern: Vec<PatternPsnr>,
    ) -> Result<RelightReport, HoldoutError> {
        let mut psnr = BTreeMap::new();
        let mut rmse = BTreeMap::new();
        for (i, (_, name)) in baselines.iter().enumerate() {
            let e = self.total[i]
                .errors()
                .map_err(metric_err(format!("{name} over all patterns")))?;
            psnr.insert((*name).to_owned(), e.psnr_db);
            rmse.insert((*name).to_owned(), e.rmse);
        }
        let mut global_rel = BTreeMap::new();
        if !self.global_patterns.is_empty() {
            for (i, (b, name)) in baselines.iter().enumerate() {
                if *b == Baseline::Direct {
                    continue;
                }
                let e = self.global[i]
                    .errors()
                    .map_err(metric_err(format!("{name} global")))?;
                global_rel.insert((*name).to_owned(), e.rel_rmse);
            }
        }
        let best_baseline_psnr = baselines
            .iter()
            .skip(1)
            .filter_map(|(_, n)| finite(&psnr, n))
            .fold(f64::NEG_INFINITY, f64::max);
        let psnr_of = |name: &str| finite(&psnr, name).unwrap_or(f64::NAN);
        let mlsss_psnr = psnr_of("mlsss");
        let margins = Margins {
            psnr_db_mlsss_minus_best_baseline: mlsss_psnr - best_baseline_psnr,
            psnr_db_mlsss_minus_homogeneous: mlsss_psnr - psnr_of("homogeneous"),
            global_rel_rmse_homogeneous_over_mlsss: ratio(&global_rel, "homogeneous", "mlsss"),
            global_rel_rmse_dipole_over_mlsss: ratio(&global_rel, "dipole", "mlsss"),
        };
        Ok(RelightReport {
            holdout_projector: k,
            patterns: patterns.iter().map(Pattern::label).collect(),
            compared_pixels: self.total.first().map_or(0, |t| t.pixels) / patterns.len().max(1),
            psnr_db: psnr,
            rmse,
            global_rel_rmse: (!global_rel.is_empty()).then_some(global_rel),
            global_truth_patterns: self.global_patterns,
            margins,
            per_pattern,
            render_seconds: self.render_seconds,
            backscatter: None,
        })
    }
}

/// `map[key]` when present and finite (a non-finite metric is null in the report).
fn finite(map: &BTreeMap<String, f64>, key: &str) -> Option<f64> {
    map.get(key).copied().filter(|v| v.is_finite())
}

fn ratio(map: &BTreeMap<String, f64>, a: &str, b: &str) -> Option<f64> {
    match (finite(map, a), finite(map, b)) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    }
}
