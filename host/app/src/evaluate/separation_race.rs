//! The separate and normals stages' variants raced on one capture (`mlsss bench
//! --separation-race CAPTURE`): run time (wall and CPU seconds of the two stages, alternated
//! over rounds so a drifting machine loads every variant alike) beside the errors each reaches
//! against the simulator's truth.
//!
//! Variants: `paper` (Nayar et al.'s separation, Lambertian photometric stereo on its direct
//! part: the paper's chain and the baseline), `dichromatic` (the kernel-aware split with one
//! body colour per image, specular photometric stereo, fused normals: the default before the
//! lobe), `lobe_with_leak` (today's default that also reads the slit sweep's kernel leak, which
//! the lobe makes moot) and `lobe` (the default).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::pipeline::normals_stage::{NormalSource, NormalsParams, PsInput, ShadingModel};
use crate::pipeline::separate_stage::{DirectModel, SeparateParams, SeparationMethod};
use crate::pipeline::{CalibrationSource, Pipeline, PipelineError, PipelineReport};

/// One raced configuration of the separate and normals stages.
#[derive(Debug, Clone)]
pub struct Variant {
    pub name: &'static str,
    pub separate: SeparateParams,
    pub normals: NormalsParams,
}

/// The raced variants (see the module documentation), the baseline first.
pub fn variants() -> Vec<Variant> {
    let paper = Variant {
        name: "paper",
        separate: SeparateParams {
            method: SeparationMethod::Nayar,
            ..SeparateParams::default()
        },
        normals: NormalsParams {
            input: PsInput::NayarDirect,
            model: ShadingModel::Lambertian,
            source: NormalSource::Photometric,
            ..NormalsParams::default()
        },
    };
    let dichromatic = Variant {
        name: "dichromatic",
        separate: SeparateParams {
            direct_model: DirectModel::Dichromatic,
            ..SeparateParams::default()
        },
        normals: NormalsParams::default(),
    };
    let lobe_with_leak = Variant {
        name: "lobe_with_leak",
        separate: SeparateParams {
            leak_with_lobe: true,
            ..SeparateParams::default()
        },
        normals: NormalsParams::default(),
    };
    let lobe = Variant {
        name: "lobe",
        separate: SeparateParams::default(),
        normals: NormalsParams::default(),
    };
    vec![paper, dichromatic, lobe_with_leak, lobe]
}

/// One run of one variant.
#[derive(Debug, Clone, Serialize)]
pub struct RaceRun {
    pub variant: String,
    pub round: usize,
    /// Wall seconds of separate + normals.
    pub wall_s: f64,
    /// CPU seconds (all threads) of separate + normals; `None` where the platform gives none.
    pub cpu_s: Option<f64>,
    /// With ground truth: the separation's and the normals' errors.
    pub direct_rel_rmse: Option<f64>,
    pub global_rel_rmse: Option<f64>,
    pub normals_mean_error_deg: Option<f64>,
}

/// Errors of the race.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RaceError {
    /// A variant's pipeline failed.
    #[error("variant {variant}: {source}")]
    Pipeline {
        variant: &'static str,
        source: PipelineError,
    },
    /// A stage folder could not be cleared for the next round.
    #[error("clearing {path}: {source}")]
    Clear {
        path: PathBuf,
        source: std::io::Error,
    },
    /// A variant's parameters could not be handed to the pipeline.
    #[error(transparent)]
    Params(#[from] serde_json::Error),
    /// The pipeline ran but did not report the separate or normals stage.
    #[error("variant {0}: no separate or normals timing in the report")]
    NoTiming(&'static str),
}

/// Races `variants` on `capture` for `rounds` rounds, each variant in its own folder under
/// `out` (decode and geometry run once per folder and are reused); `progress` hears of each run.
pub fn race(
    capture: &Path,
    out: &Path,
    calibration: &CalibrationSource,
    variants: &[Variant],
    rounds: usize,
    progress: &dyn Fn(&RaceRun),
) -> Result<Vec<RaceRun>, RaceError> {
    let mut runs = Vec::new();
    for round in 1..=rounds {
        for variant in variants {
            let run = race_once(
                capture,
                &out.join(variant.name),
                calibration,
                variant,
                round,
            )?;
            progress(&run);
            runs.push(run);
        }
    }
    Ok(runs)
}

fn race_once(
    capture: &Path,
    dir: &Path,
    calibration: &CalibrationSource,
    variant: &Variant,
    round: usize,
) -> Result<RaceRun, RaceError> {
    let failed = |source| RaceError::Pipeline {
        variant: variant.name,
        source,
    };
    // The raced stages run every round: their cache records go.
    for stage in ["separate", "normals"] {
        let path = dir.join(stage);
        if path.is_dir() {
            std::fs::remove_dir_all(&path).map_err(|source| RaceError::Clear { path, source })?;
        }
    }
    let mut pipeline = Pipeline::new(capture, dir, calibration).map_err(failed)?;
    pipeline.set_params("separate", serde_json::to_value(&variant.separate)?);
    pipeline.set_params("normals", serde_json::to_value(&variant.normals)?);
    let report = pipeline.run_until("normals").map_err(failed)?;
    run_of(variant.name, round, &report).ok_or(RaceError::NoTiming(variant.name))
}

fn run_of(variant: &str, round: usize, report: &PipelineReport) -> Option<RaceRun> {
    let stages = ["separate", "normals"];
    let wall_s = stages
        .iter()
        .map(|s| report.timing_s.get(*s).copied())
        .sum::<Option<f64>>()?;
    let cpu_s = stages
        .iter()
        .map(|s| report.timing_cpu_s.get(*s).copied())
        .sum::<Option<f64>>();
    let separation = report.separate.as_ref().and_then(|s| s.truth);
    Some(RaceRun {
        variant: variant.to_owned(),
        round,
        wall_s,
        cpu_s,
        direct_rel_rmse: separation.map(|e| e.direct_rel_rmse),
        global_rel_rmse: separation.map(|e| e.global_rel_rmse),
        normals_mean_error_deg: report
            .normals
            .as_ref()
            .and_then(|n| n.truth)
            .map(|t| t.mean_angular_error_deg),
    })
}

/// Per variant, in the order raced: the median CPU and wall seconds over the rounds, their
/// ratios to the first variant's, and the errors (the same every round).
#[derive(Debug, Clone, Serialize)]
pub struct RaceSummary {
    pub variant: String,
    pub rounds: usize,
    pub median_cpu_s: Option<f64>,
    pub median_wall_s: f64,
    pub cpu_ratio_to_baseline: Option<f64>,
    pub wall_ratio_to_baseline: f64,
    pub direct_rel_rmse: Option<f64>,
    pub global_rel_rmse: Option<f64>,
    pub normals_mean_error_deg: Option<f64>,
}

/// The summary of `runs` (see [`RaceSummary`]).
pub fn summarise(runs: &[RaceRun]) -> Vec<RaceSummary> {
    let mut names: Vec<&str> = Vec::new();
    for run in runs {
        if !names.contains(&run.variant.as_str()) {
            names.push(&run.variant);
        }
    }
    let mut rows: Vec<RaceSummary> = names
        .iter()
        .filter_map(|name| {
            let mine: Vec<&RaceRun> = runs.iter().filter(|r| r.variant == *name).collect();
            let last = mine.last()?;
            let cpu: Option<Vec<f64>> = mine.iter().map(|r| r.cpu_s).collect();
            Some(RaceSummary {
                variant: (*name).to_owned(),
                rounds: mine.len(),
                median_cpu_s: cpu.map(median),
                median_wall_s: median(mine.iter().map(|r| r.wall_s).collect()),
                cpu_ratio_to_baseline: None,
                wall_ratio_to_baseline: 1.0,
                direct_rel_rmse: last.direct_rel_rmse,
                global_rel_rmse: last.global_rel_rmse,
                normals_mean_error_deg: last.normals_mean_error_deg,
            })
        })
        .collect();
    if let Some((baseline_cpu, baseline_wall)) =
        rows.first().map(|b| (b.median_cpu_s, b.median_wall_s))
    {
        for row in &mut rows {
            row.cpu_ratio_to_baseline = row
                .median_cpu_s
                .zip(baseline_cpu)
                .filter(|(_, b)| *b > 0.0)
                .map(|(c, b)| c / b);
            row.wall_ratio_to_baseline = row.median_wall_s / baseline_wall.max(f64::MIN_POSITIVE);
        }
    }
    rows
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => values[n / 2],
        n => (values[n / 2 - 1] + values[n / 2]) / 2.0,
    }
}

/// The summary as CSV (header first; empty fields where a value is missing).
pub fn to_csv(rows: &[RaceSummary]) -> String {
    let field = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.4}"));
    let mut out = String::from(
        "variant,rounds,median_cpu_s,median_wall_s,cpu_ratio_to_baseline,wall_ratio_to_baseline,\
         direct_rel_rmse,global_rel_rmse,normals_mean_error_deg\n",
    );
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{},{:.4},{},{:.4},{},{},{}",
            r.variant,
            r.rounds,
            field(r.median_cpu_s),
            r.median_wall_s,
            field(r.cpu_ratio_to_baseline),
            r.wall_ratio_to_baseline,
            field(r.direct_rel_rmse),
            field(r.global_rel_rmse),
            field(r.normals_mean_error_deg),
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(variant: &str, round: usize, cpu: f64, wall: f64) -> RaceRun {
        RaceRun {
            variant: variant.into(),
            round,
            wall_s: wall,
            cpu_s: Some(cpu),
            direct_rel_rmse: Some(0.1),
            global_rel_rmse: None,
            normals_mean_error_deg: Some(1.0),
        }
    }

    #[test]
    fn the_summary_takes_medians_per_variant_and_ratios_to_the_first() {
        let runs = [
            run("paper", 1, 4.0, 2.0),
            run("lobe", 1, 9.0, 5.0),
            run("paper", 2, 5.0, 3.0),
            run("lobe", 2, 7.0, 4.0),
            run("paper", 3, 4.5, 2.5),
            run("lobe", 3, 8.0, 4.5),
        ];
        let rows = summarise(&runs);
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].variant, "paper");
        assert_eq!(rows[0].median_cpu_s, Some(4.5));
        assert_eq!(rows[1].median_cpu_s, Some(8.0));
        assert_eq!(rows[1].median_wall_s, 4.5);
        assert!((rows[1].cpu_ratio_to_baseline.unwrap() - 8.0 / 4.5).abs() < 1e-12);
        assert!((rows[1].wall_ratio_to_baseline - 4.5 / 2.5).abs() < 1e-12);
        let csv = to_csv(&rows);
        assert!(
            csv.lines()
                .nth(2)
                .unwrap()
                .starts_with("lobe,3,8.0000,4.5000,1.7778")
        );
        assert!(
            csv.contains(",,"),
            "a missing error is an empty field: {csv}"
        );
    }
}
