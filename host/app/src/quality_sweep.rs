//! The runtime-versus-error sweep behind `mlsss bench`: the fit and render knobs varied one at a
//! time from the defaults (components, EM tolerance and iteration cap, profile sampling, kernel
//! truncation) plus the capture resolution, each scored by the held-out relighting error, and
//! the Pareto front of (seconds, error).
//!
//! Runtime of a configuration = fit stage + rendering of the held-out projector's evaluation
//! patterns with MLSSS (decode, geometry, separation, normals and profiles do not depend on the
//! knobs and are cached across configurations). Error = relative RMSE of the rendered subsurface
//! light against the simulator's truth (`global_rel_rmse`), and the total-image RMSE against the
//! recorded frames.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;
use serde_json::{Value, json};

use crate::evaluate::holdout::{HoldoutError, evaluate_holdout};
use crate::pipeline::fit_stage::{FitParams, model_path};
use crate::pipeline::{CalibrationSource, Pipeline, PipelineError};
use crate::report::plot::{Plot, PlotError, Style};
use mlsss_core::capture::{Capture, CaptureError};
use mlsss_layer_model::model_file::{Baseline, ModelFileError, SubsurfaceModel};
use mlsss_layer_model::render::RenderOptions;

/// Errors of the sweep.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SweepError {
    /// The pipeline failed for a configuration.
    #[error("configuration {config}: {source}")]
    Pipeline {
        config: String,
        source: PipelineError,
    },
    /// The model file of a configuration could not be read.
    #[error("configuration {config}: {source}")]
    Model {
        config: String,
        source: ModelFileError,
    },
    /// The held-out evaluation failed.
    #[error("configuration {config}: {source}")]
    Holdout {
        config: String,
        source: HoldoutError,
    },
    /// A capture could not be opened.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// The plot could not be drawn.
    #[error(transparent)]
    Plot(#[from] PlotError),
    /// An output file could not be written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// One configuration of the sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SweepConfig {
    /// Which knob this configuration varies (`default` for the reference).
    pub knob: String,
    /// The knob's value, as text.
    pub value: String,
    pub components: usize,
    pub tolerance: f64,
    pub max_iterations: usize,
    /// Profile sampling: one fit per `block x block` pixels.
    pub block: usize,
    pub truncate_sigmas: f64,
    /// Index of the capture (resolution) in the sweep's capture list.
    pub capture: usize,
}

/// A measured configuration.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SweepRow {
    #[serde(flatten)]
    pub config: SweepConfig,
    /// Camera size of the capture.
    pub camera: String,
    pub fit_s: f64,
    pub render_s: f64,
    pub seconds: f64,
    pub psnr_db: f64,
    pub rmse: f64,
    pub global_rel_rmse: Option<f64>,
    /// On the Pareto front of (seconds, error).
    pub pareto: bool,
}

/// The sweep's plan: the reference configuration (the demo's fit knobs,
/// [`crate::demo::quick_fit_params`]), then each knob varied alone.
pub fn plan(quick: bool, captures: usize) -> Vec<SweepConfig> {
    let reference = crate::demo::quick_fit_params();
    let base = SweepConfig {
        knob: "default".into(),
        value: "-".into(),
        components: reference.components,
        tolerance: reference.tolerance,
        max_iterations: reference.max_iterations,
        block: reference.block,
        truncate_sigmas: RenderOptions::default().truncate_sigmas,
        capture: 0,
    };
    let mut out = vec![base.clone()];
    let vary = |knob: &str, value: String, f: &dyn Fn(&mut SweepConfig)| {
        let mut c = base.clone();
        c.knob = knob.into();
        c.value = value;
        f(&mut c);
        c
    };
    let components: &[usize] = if quick { &[2, 8] } else { &[2, 8, 20] };
    for &n in components {
        out.push(vary("components", n.to_string(), &|c| c.components = n));
    }
    // Around the default tolerance (1e-5). Looser costs little held-out error but some
    // back-scatter (see `FitParams::tolerance`), which this table does not show.
    let em: &[(f64, usize)] = if quick {
        &[(1e-4, 200)]
    } else {
        &[(1e-4, 200), (3e-5, 200), (1e-6, 200)]
    };
    for &(tol, it) in em {
        out.push(vary("em", format!("tol {tol:e} / {it} it"), &|c| {
            c.tolerance = tol;
            c.max_iterations = it;
        }));
    }
    let blocks: &[usize] = if quick { &[3, 12] } else { &[1, 3, 12] };
    for &b in blocks {
        out.push(vary("profile_block", b.to_string(), &|c| c.block = b));
    }
    let truncations: &[f64] = if quick {
        &[2.0, 5.0]
    } else {
        &[1.5, 2.0, 2.5, 5.0]
    };
    for &t in truncations {
        out.push(vary("truncate_sigmas", t.to_string(), &|c| {
            c.truncate_sigmas = t
        }));
    }
    for i in 1..captures {
        out.push(vary("resolution", format!("capture {i}"), &|c| {
            c.capture = i
        }));
    }
    out
}

/// Marks the rows on the Pareto front: no other row is both faster and more accurate.
pub fn mark_pareto(rows: &mut [SweepRow], error: impl Fn(&SweepRow) -> f64) {
    let points: Vec<(f64, f64)> = rows.iter().map(|r| (r.seconds, error(r))).collect();
    for (i, row) in rows.iter_mut().enumerate() {
        let (t, e) = points[i];
        row.pareto = e.is_finite()
            && !points
                .iter()
                .enumerate()
                .any(|(j, &(tj, ej))| j != i && tj <= t && ej <= e && (tj < t || ej < e));
    }
}

/// The error a row is ranked by: the subsurface error against the truth when known, else the
/// total RMSE.
pub fn ranking_error(row: &SweepRow) -> f64 {
    row.global_rel_rmse.unwrap_or(row.rmse)
}

/// CSV text of the rows (header first).
pub fn to_csv(rows: &[SweepRow]) -> String {
    let mut s = String::from(
        "knob,value,camera,components,tolerance,max_iterations,block,truncate_sigmas,\
         fit_s,render_s,seconds,psnr_db,rmse,global_rel_rmse,pareto\n",
    );
    for r in rows {
        let c = &r.config;
        let _ = writeln!(
            s,
            "{},\"{}\",{},{},{:e},{},{},{},{:.4},{:.4},{:.4},{:.4},{:.6},{},{}",
            c.knob,
            c.value,
            r.camera,
            c.components,
            c.tolerance,
            c.max_iterations,
            c.block,
            c.truncate_sigmas,
            r.fit_s,
            r.render_s,
            r.seconds,
            r.psnr_db,
            r.rmse,
            r.global_rel_rmse
                .map_or(String::new(), |g| format!("{g:.6}")),
            r.pareto
        );
    }
    s
}

/// The runtime-vs-error plot with the Pareto front drawn as a line.
pub fn pareto_plot(rows: &[SweepRow]) -> Plot {
    let all: Vec<(f64, f64)> = rows.iter().map(|r| (r.seconds, ranking_error(r))).collect();
    let mut front: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| r.pareto)
        .map(|r| (r.seconds, ranking_error(r)))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    let y = if rows.iter().any(|r| r.global_rel_rmse.is_some()) {
        "subsurface rel. RMSE"
    } else {
        "RMSE"
    };
    Plot::new("runtime vs held-out error", "fit + render time (s)", y)
        .with_series("configurations", all, Style::Points)
        .with_series("Pareto front", front, Style::LineAndPoints)
}

/// What the sweep runs on.
#[derive(Debug, Clone)]
pub struct SweepInputs {
    /// Captures (index 0 = reference resolution), each with its pipeline output folder.
    pub captures: Vec<(PathBuf, PathBuf)>,
    pub calibration: CalibrationSource,
    pub holdout: usize,
}

/// Runs `configs` and returns the rows with the Pareto front marked. `on_config` is called
/// before each configuration (progress).
pub fn run_sweep(
    inputs: &SweepInputs,
    configs: &[SweepConfig],
    on_config: &dyn Fn(usize, &SweepConfig),
) -> Result<Vec<SweepRow>, SweepError> {
    let mut rows = Vec::with_capacity(configs.len());
    for (i, config) in configs.iter().enumerate() {
        on_config(i, config);
        let name = format!("{}={}", config.knob, config.value);
        let (capture_dir, out) = &inputs.captures[config.capture];
        let mut pipeline =
            Pipeline::new(capture_dir, out, &inputs.calibration).map_err(|source| {
                SweepError::Pipeline {
                    config: name.clone(),
                    source,
                }
            })?;
        let params = FitParams {
            holdout: Some(inputs.holdout),
            components: config.components,
            tolerance: config.tolerance,
            max_iterations: config.max_iterations,
            block: config.block,
            dipole: false,
            ..FitParams::default()
        };
        pipeline.set_params("fit", serde_json::to_value(&params).unwrap_or(Value::Null));
        let start = Instant::now();
        let report = pipeline
            .run_until("fit")
            .map_err(|source| SweepError::Pipeline {
                config: name.clone(),
                source,
            })?;
        // The stage's own time when it ran; the wall time when it came from the cache of an
        // identical configuration would be 0, so take the recorded stage time.
        let fit_s = report
            .timing_s
            .get("fit")
            .copied()
            .unwrap_or_else(|| start.elapsed().as_secs_f64());
        let model =
            SubsurfaceModel::load(&model_path(out)).map_err(|source| SweepError::Model {
                config: name.clone(),
                source,
            })?;
        let capture = Capture::open(capture_dir)?;
        let render = RenderOptions {
            truncate_sigmas: config.truncate_sigmas,
            ..RenderOptions::default()
        };
        let eval = evaluate_holdout(
            &capture,
            &model,
            inputs.holdout,
            &[Baseline::Mlsss],
            &render,
        )
        .map_err(|source| SweepError::Holdout {
            config: name.clone(),
            source,
        })?;
        let r = &eval.report;
        rows.push(SweepRow {
            config: config.clone(),
            camera: format!("{}x{}", model.header.width, model.header.height),
            fit_s,
            render_s: eval.render_seconds,
            seconds: fit_s + eval.render_seconds,
            psnr_db: r
                .psnr("mlsss")
                .filter(|v| v.is_finite())
                .unwrap_or(f64::NAN),
            rmse: r
                .rmse_of("mlsss")
                .filter(|v| v.is_finite())
                .unwrap_or(f64::NAN),
            global_rel_rmse: r.global_rel_rmse_of("mlsss").filter(|v| v.is_finite()),
            pareto: false,
        });
    }
    mark_pareto(&mut rows, ranking_error);
    Ok(rows)
}

/// Writes `bench.csv` and `pareto.png` into `dir`; returns their paths.
pub fn write_outputs(dir: &Path, rows: &[SweepRow]) -> Result<(PathBuf, PathBuf), SweepError> {
    let csv = dir.join("bench.csv");
    mlsss_core::atomic_file::write_bytes_atomically(&csv, to_csv(rows)).map_err(|source| {
        SweepError::Io {
            path: csv.clone(),
            source,
        }
    })?;
    let png = dir.join("pareto.png");
    pareto_plot(rows).save_png(&png)?;
    Ok((csv, png))
}

/// The JSON summary of a sweep.
pub fn summary(rows: &[SweepRow], csv: &Path, png: &Path) -> Value {
    json!({
        "configurations": rows.len(),
        "rows": rows,
        "pareto": rows.iter().filter(|r| r.pareto).map(|r| format!("{}={}", r.config.knob, r.config.value)).collect::<Vec<_>>(),
        "csv": csv,
        "plot": png,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(knob: &str, seconds: f64, err: f64) -> SweepRow {
        let mut config = plan(true, 1)[0].clone();
        config.knob = knob.into();
        SweepRow {
            config,
            camera: "4x4".into(),
            fit_s: seconds,
            render_s: 0.0,
            seconds,
            psnr_db: 30.0,
            rmse: err,
            global_rel_rmse: Some(err),
            pareto: false,
        }
    }

    #[test]
    fn pareto_front_keeps_only_undominated_rows() {
        let mut rows = vec![
            row("a", 1.0, 0.5),
            row("b", 2.0, 0.3),
            row("c", 3.0, 0.4), // dominated by b
            row("d", 4.0, 0.1),
            row("e", 1.0, 0.6), // dominated by a
            row("f", 5.0, f64::NAN),
        ];
        mark_pareto(&mut rows, ranking_error);
        let front: Vec<&str> = rows
            .iter()
            .filter(|r| r.pareto)
            .map(|r| r.config.knob.as_str())
            .collect();
        assert_eq!(front, vec!["a", "b", "d"]);
        let csv = to_csv(&rows);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 7);
        let columns = lines[0].split(',').count();
        assert!(
            lines.iter().all(|l| l.split(',').count() == columns),
            "{csv}"
        );
        assert!(lines[1].ends_with(",true") && lines[3].ends_with(",false"));
        assert!(pareto_plot(&rows).render().is_ok());
    }

    #[test]
    fn the_plan_varies_one_knob_at_a_time() {
        let p = plan(true, 2);
        assert_eq!(p[0].knob, "default");
        for c in &p[1..] {
            let differs = [
                c.components != p[0].components,
                c.tolerance != p[0].tolerance || c.max_iterations != p[0].max_iterations,
                c.block != p[0].block,
                c.truncate_sigmas != p[0].truncate_sigmas,
                c.capture != p[0].capture,
            ];
            assert_eq!(differs.iter().filter(|d| **d).count(), 1, "{c:?}");
        }
        assert!(p.iter().any(|c| c.knob == "resolution"));
        assert!(plan(false, 3).len() > p.len());
    }
}
