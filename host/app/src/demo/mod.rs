//! The end-to-end demonstration (`mlsss demo`): simulate a scan and chessboard calibration poses
//! in the virtual booth, calibrate the booth from the poses, process the scan with one projector
//! held out of the fit, relight that projector from the model and evaluate everything against the
//! simulator's truth.
//!
//! Timing keys (wall clock, seconds): `simulate` (the scan, with the calibration poses simulated
//! and calibrated beside it), of which `simulate_scan`, `simulate_calibration` and `calibrate`
//! are each step's own time (the last two overlap the first, so they do not add up to
//! `simulate`); one per pipeline stage (the `fit` stage includes its own figures and check
//! renders), `eval` (the held-out evaluation: loading the model beside reading the frames,
//! rendering, metrics) of which
//! `render` is the rendering, `total` (wall clock of everything).
//!
//! `timing_cpu_s` (CPU seconds, user + system, all threads): `simulate` (the scan, the poses and
//! their calibration together: they share the cores, so the process's CPU time cannot be split
//! between them), one per pipeline stage (the pipeline's own `timing_cpu_s`), `eval`,
//! `backscatter` and `total`. Why: on a shared machine a step's wall clock moves with the other
//! processes' load (the quick demo took 29-78 s wall on one day's VM), its CPU time much less.
//!
//! ```text
//! OUT/
//!   capture/              the simulated scan (frames + truth/)
//!   calibration-poses/    pose00, pose01, ... (only with an estimated calibration; frames and
//!                         manifest, no truth/)
//!   calibration.json      the estimated calibration, in the truth's world frame (see below)
//!   processed/            the pipeline's stage folders and report.json
//!   demo.json             the report (what `--json` prints)
//!   report.html           the HTML report (figures, metrics, timings)
//! ```
//!
//! The estimated calibration lives in the camera's frame; it is re-expressed in the booth's world
//! frame through the TRUE camera pose before processing
//! ([`crate::evaluate::calibration_error::align_world_frame`]): the world frame is a free choice
//! and the truth's maps (points, normals) are stored in the booth's frame. Nothing the calibration
//! measured changes.

pub mod html_report;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::evaluate::backscatter::{BackscatterError, evaluate_backscatter};
use crate::evaluate::calibration_error::{
    CalibrationErrorError, CalibrationErrors, align_world_frame, calibration_errors,
};
use crate::evaluate::holdout::{HeldOutImages, HoldoutError, RelightReport, evaluate_read_holdout};
use crate::pipeline::decode_stage::ProjectorDecodeReport;
use crate::pipeline::fit_stage::{FitParams, FitReport, model_path};
use crate::pipeline::geometry_stage::GeometryReport;
use crate::pipeline::normals_stage::NormalsReport;
use crate::pipeline::profiles_stage::ProfilesReport;
use crate::pipeline::{CalibrationSource, Pipeline, PipelineError, PipelineReport};
use crate::pose_calibration::{PoseCalibrationError, calibrate_poses};
use mlsss_core::booth::Booth;
use mlsss_core::calibration::{Calibration, CalibrationError};
use mlsss_core::capture::{Capture, CaptureError, Pattern, ProjectorExposure, truth};
use mlsss_core::resources::{cpu_seconds, peak_memory_mb};
use mlsss_layer_model::model_file::{Baseline, ModelFileError, SubsurfaceModel};
use mlsss_layer_model::render::RenderOptions;
use mlsss_virtual_booth::{
    NoProgress, Progress, ResponseCache, SimulationOptions, SkinPreset, SubjectKind,
    VirtualBoothError, scaled_booth, simulate_calibration, simulate_scan,
};
use mlsss_vision::chessboard_calibration::pose_measurement::{PoseLayout, PoseMeasurementError};
use mlsss_vision::chessboard_calibration::procam::{
    BoardSpec, ProcamError, ProcamOptions, distortion_term_names,
};
use mlsss_vision::photometry::response::{LevelFrames, ResponseError, estimate_responses};

/// File name of the report in the output folder.
pub const REPORT_FILE: &str = "demo.json";
/// File name of the back-scatter plot in the processed folder.
pub const BACKSCATTER_PLOT: &str = "backscatter.png";
/// File name of the HTML report in the output folder.
pub const HTML_FILE: &str = "report.html";

/// Errors of the demonstration.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DemoError {
    /// The virtual booth failed.
    #[error("simulation failed")]
    Simulation(#[from] VirtualBoothError),
    /// A calibration pose could not be measured.
    #[error("measuring a calibration pose failed")]
    PoseMeasurement(#[from] PoseMeasurementError),
    /// The calibration from the poses failed (typically: the board was not found in enough poses
    /// because the camera is too small, as at `--scale-down 4`).
    #[error(
        "calibration from the chessboard poses failed (a camera shrunk by --scale-down 4 or more \
         is too small to find the board: use --calib truth, or a smaller --scale-down)"
    )]
    Procam(#[from] ProcamError),
    /// The projector responses could not be estimated.
    #[error("projector response estimation failed")]
    Response(#[from] ResponseError),
    /// A calibration file could not be read or written.
    #[error(transparent)]
    CalibrationFile(#[from] CalibrationError),
    /// The estimate and the truth describe different booths.
    #[error("comparing the calibration with the truth failed")]
    CalibrationComparison(#[from] CalibrationErrorError),
    /// A capture could not be read.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// The processing pipeline failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// The fitted model could not be read.
    #[error("reading the fitted model failed")]
    Model(#[from] ModelFileError),
    /// The held-out evaluation failed.
    #[error("held-out evaluation failed")]
    Holdout(#[from] HoldoutError),
    /// The back-scatter evaluation failed.
    #[error("back-scatter evaluation failed")]
    Backscatter(#[from] BackscatterError),
    /// A plot could not be written.
    #[error("writing a plot failed")]
    Plot(#[from] crate::report::plot::PlotError),
    /// The HTML report could not be written.
    #[error("writing the HTML report failed")]
    Report(#[from] html_report::DemoReportError),
    /// The output folder cannot be used.
    #[error("{path}: {reason}")]
    Output { path: PathBuf, reason: String },
    /// A file of the output could not be written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// An option is out of range.
    #[error("{option}: {reason}")]
    InvalidOption {
        option: &'static str,
        reason: String,
    },
}

impl From<PoseCalibrationError> for DemoError {
    fn from(e: PoseCalibrationError) -> Self {
        match e {
            PoseCalibrationError::Measurement(e) => DemoError::PoseMeasurement(e),
            PoseCalibrationError::Procam(e) => DemoError::Procam(e),
            other => DemoError::InvalidOption {
                option: "--poses",
                reason: other.to_string(),
            },
        }
    }
}

/// Where the demonstration's calibration comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CalibrationMode {
    /// Simulated chessboard poses, calibrated like real ones (the honest path).
    Estimated { poses: usize },
    /// The simulator's exact calibration (isolates the rest of the pipeline from calibration
    /// error).
    Truth,
}

/// What to run.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    pub booth: Booth,
    pub subject: SubjectKind,
    pub skin: SkinPreset,
    pub seed: u64,
    /// Projector held out of the fit and relit for the evaluation.
    pub holdout: usize,
    pub calibration: CalibrationMode,
    /// Fit stage parameters (`holdout` is set from [`Self::holdout`]).
    pub fit: FitParams,
    /// Renderer options of the held-out relighting.
    pub render: RenderOptions,
    /// Monte Carlo photons per response (`None`: the simulator's default for the booth).
    pub photons: Option<u64>,
    /// Monte Carlo response cache folder (`None`: the simulator's default).
    pub cache: Option<PathBuf>,
    /// Meter the subject and expose each projector to fit it (off: the booth's nominal exposure
    /// for every frame, as the demo ran before metering).
    pub metering: bool,
    pub out: PathBuf,
}

impl DemoOptions {
    /// Defaults: the built-in booth (`quick` or full size) shrunk by `scale_down`, a light-skinned
    /// head, seed 1, projector 3 held out, calibration estimated from 5 poses.
    pub fn new(quick: bool, scale_down: u32, out: &Path) -> Self {
        let mut booth = Booth::builtin(quick);
        if scale_down > 1 {
            booth = scaled_booth(&booth, scale_down);
        }
        Self {
            booth,
            subject: SubjectKind::Head,
            skin: SkinPreset::LIGHT,
            seed: 1,
            holdout: 3,
            calibration: CalibrationMode::Estimated { poses: 5 },
            fit: quick_fit_params(),
            render: RenderOptions::default(),
            photons: None,
            metering: true,
            cache: None,
            out: out.to_owned(),
        }
    }
}

/// The fit knobs of the demonstration: 4 starting components per fit and one EM fit per 6x6
/// pixel tile (each pixel keeps its own amplitude) — the operating point the `fit` engineer
/// measured on the quick head (fit ~1 min in a dev build); the paper's 20 components per pixel
/// cost minutes even on the tiny test scene. `mlsss bench` measures what the knobs cost and buy.
pub fn quick_fit_params() -> FitParams {
    FitParams {
        components: 4,
        block: 6,
        heldout_check: false, // the demo's evaluation renders the held-out projector itself
        ..FitParams::default()
    }
}

/// What the demonstration produced.
#[derive(Debug, Clone)]
pub struct DemoOutcome {
    /// The report (also in `OUT/demo.json`).
    pub report: DemoReport,
    pub capture: PathBuf,
    pub processed: PathBuf,
}

/// The demonstration's report (`OUT/demo.json`, what `mlsss demo --json` prints; its keys are
/// documented in the README). Every section is optional so that `mlsss eval --report` can draw
/// the HTML report of a relighting alone; the demo fills them all.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DemoReport {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub demo: Option<DemoInfo>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<CalibrationReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decode: Option<DecodeSummary>,
    /// The geometry's depth error against the truth (also in `geometry`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_rmse_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub geometry: Option<GeometryReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub separation: Option<SeparationSummary>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normals: Option<NormalsReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relight: Option<RelightReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fit: Option<FitReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profiles: Option<ProfilesReport>,
    /// Wall-clock seconds per step (see the module documentation).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub timing_s: BTreeMap<String, f64>,
    /// CPU seconds per step (see the module documentation); empty where the platform does not
    /// report the process's CPU time.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub timing_cpu_s: BTreeMap<String, f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peak_memory_mb: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report_json: Option<PathBuf>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report_html: Option<PathBuf>,
}

/// What the demonstration ran.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DemoInfo {
    pub booth: String,
    /// Camera width and height, px.
    pub camera: [u32; 2],
    pub subject: String,
    pub skin: String,
    pub seed: u64,
    pub holdout_projector: usize,
    pub calibration: CalibrationMode,
    pub monte_carlo: MonteCarloCounts,
    pub out: PathBuf,
    /// Each projector's exposure, from the capture's metering (empty: nominal exposure).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub exposure: Vec<ProjectorExposure>,
}

/// Monte Carlo responses reused from the cache and computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct MonteCarloCounts {
    pub cached: usize,
    pub computed: usize,
}

/// The calibration used: `source` is `truth` or `estimated`; an estimate has its report, file
/// and errors against the truth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationReport {
    pub source: String,
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub estimate: Option<PoseCalibrationReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<PathBuf>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub errors: Option<CalibrationErrors>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub response_errors: Option<Vec<ResponseErrors>>,
}

/// A calibration from chessboard poses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseCalibrationReport {
    pub poses_used: usize,
    pub poses_total: usize,
    pub camera_rms_px: f64,
    pub projector_rms_px: Vec<f64>,
    pub stereo_rms_px: f64,
    /// Per device (camera first), the distortion terms estimated.
    pub distortion_terms: Vec<Vec<String>>,
    /// The projector responses (`photometry::response::ResponseFit` per projector).
    pub responses: Value,
}

/// Estimated projector response against the truth, percent.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ResponseErrors {
    pub gamma_rel_pct: f64,
    pub black_level_rel_pct: f64,
}

/// The decode stage's results, with means over the projectors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecodeSummary {
    pub exact_fraction: Option<f64>,
    pub valid_fraction: Option<f64>,
    pub wrong_fraction: Option<f64>,
    pub projectors: Vec<ProjectorDecodeReport>,
}

/// The separation's errors against the truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SeparationSummary {
    pub global_rel_rmse: Option<f64>,
    pub direct_rel_rmse: Option<f64>,
    pub total_rel_rmse: Option<f64>,
    /// The separation method run (`kernel` or `nayar`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<crate::pipeline::separate_stage::SeparationMethod>,
    /// The Nayar baseline's errors on the same frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nayar_global_rel_rmse: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nayar_direct_rel_rmse: Option<f64>,
}

/// Wall-clock and CPU seconds per step.
#[derive(Debug, Default)]
struct Timings {
    wall: BTreeMap<String, f64>,
    cpu: BTreeMap<String, f64>,
}

impl Timings {
    /// Runs `f`, adding its wall-clock and CPU seconds to `key`.
    fn time<T>(&mut self, key: &str, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let cpu = cpu_seconds();
        let out = f();
        self.add(key, start.elapsed().as_secs_f64());
        self.add_cpu_since(key, cpu);
        out
    }

    fn add(&mut self, key: &str, seconds: f64) {
        *self.wall.entry(key.to_owned()).or_insert(0.0) += seconds;
    }

    fn add_cpu(&mut self, key: &str, seconds: f64) {
        *self.cpu.entry(key.to_owned()).or_insert(0.0) += seconds;
    }

    /// Adds the process's CPU seconds since the reading `start` to `key` (nothing without a
    /// reading).
    fn add_cpu_since(&mut self, key: &str, start: Option<f64>) {
        if let (Some(start), Some(now)) = (start, cpu_seconds()) {
            self.add_cpu(key, now - start);
        }
    }
}

/// Checks the options and prepares the output folder: a folder that exists must be empty or a
/// previous demonstration's (it holds `demo.json` or the demo's sub-folders), whose outputs are
/// then replaced.
fn prepare_output(opts: &DemoOptions) -> Result<(), DemoError> {
    let projectors = opts.booth.projectors.len();
    if projectors < 2 || opts.holdout >= projectors {
        return Err(DemoError::InvalidOption {
            option: "--holdout",
            reason: format!(
                "projector {} does not exist or leaves no training projector (the booth has {projectors})",
                opts.holdout
            ),
        });
    }
    if let CalibrationMode::Estimated { poses } = opts.calibration
        && poses < 3
    {
        return Err(DemoError::InvalidOption {
            option: "--poses",
            reason: format!("a calibration needs at least 3 chessboard poses, got {poses}"),
        });
    }
    let out = &opts.out;
    let io = |source| DemoError::Io {
        path: out.clone(),
        source,
    };
    let owned = [
        "capture",
        "calibration-poses",
        "calibration.json",
        "processed",
        "report.html",
    ];
    if out.exists() {
        let entries: Vec<_> = std::fs::read_dir(out)
            .map_err(io)?
            .filter_map(Result::ok)
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        let ours = |name: &str| name == REPORT_FILE || owned.contains(&name);
        if !entries.is_empty() && !entries.iter().any(|n| ours(n)) {
            return Err(DemoError::Output {
                path: out.clone(),
                reason: "exists and is not a demo output folder: choose an empty or new --out"
                    .into(),
            });
        }
        for name in owned.iter().chain([REPORT_FILE].iter()) {
            let p = out.join(name);
            let removed = if p.is_dir() {
                std::fs::remove_dir_all(&p)
            } else if p.exists() {
                std::fs::remove_file(&p)
            } else {
                Ok(())
            };
            removed.map_err(|source| DemoError::Io { path: p, source })?;
        }
    }
    std::fs::create_dir_all(out).map_err(io)
}

fn simulation_options(opts: &DemoOptions, subject: SubjectKind) -> SimulationOptions {
    let mut sim = SimulationOptions::for_booth(&opts.booth, subject, opts.skin, opts.seed);
    sim.metering = opts.metering;
    if let Some(p) = opts.photons {
        sim.mc.photons = p;
    }
    if let Some(dir) = &opts.cache {
        sim.cache = ResponseCache::new(dir);
    }
    sim
}

/// Chessboard layout of a simulated calibration pose (from its manifest).
fn board_of(pose: &Path) -> Result<BoardSpec, DemoError> {
    let capture = Capture::open(pose)?;
    BoardSpec::from_manifest(&capture.manifest).ok_or_else(|| DemoError::Output {
        path: pose.to_owned(),
        reason: "capture.json has no source.board (inner_corners, square_mm)".into(),
    })
}

/// The full-field levels a projector response is estimated from.
fn response_level(pattern: &Pattern) -> Option<f64> {
    match *pattern {
        Pattern::White => Some(1.0),
        Pattern::Black => Some(0.0),
        Pattern::Grey { level_milli } => Some(f64::from(level_milli) / 1000.0),
        _ => None,
    }
}

fn level_frames(pose: &Path) -> Result<Vec<LevelFrames>, DemoError> {
    let capture = Capture::open(pose)?;
    (0..capture.manifest.booth.projectors.len())
        .map(|k| {
            let mut frames = LevelFrames::default();
            for spec in capture.manifest.plan.for_projector(k as u8) {
                if let Some(l) = response_level(&spec.pattern) {
                    frames.frames.push((l, capture.read(spec)?));
                }
            }
            Ok(frames)
        })
        .collect()
}

/// Calibrates the booth from the pose folders: geometry ([`calibrate_poses`]) and projector
/// responses; returns the calibration (camera frame) and its report.
fn calibrate_from_poses(
    poses: &[PathBuf],
) -> Result<(Calibration, PoseCalibrationReport), DemoError> {
    let first = poses.first().ok_or(PoseCalibrationError::NoPoses)?;
    let board = board_of(first)?;
    let result = calibrate_poses(
        poses,
        PoseLayout::Capture,
        &board,
        &ProcamOptions::default(),
        &|| {},
    )?
    .result;
    // Reading the grey-level frames (PNG decoding) is most of this step: one pose per task.
    let levels = poses
        .par_iter()
        .map(|p| level_frames(p))
        .collect::<Result<Vec<_>, _>>()?;
    let responses = estimate_responses(&levels)?;
    let mut calibration = result.calibration.clone();
    for (p, fit) in calibration.projectors.iter_mut().zip(&responses) {
        p.response = Some(fit.response());
    }
    let report = PoseCalibrationReport {
        poses_used: result.poses.iter().filter(|p| p.used).count(),
        poses_total: result.poses.len(),
        camera_rms_px: result.camera_rms_px,
        projector_rms_px: result.projector_rms_px.clone(),
        stereo_rms_px: result.stereo_rms_px,
        distortion_terms: result
            .distortion_terms
            .iter()
            .map(|t| {
                distortion_term_names(t)
                    .into_iter()
                    .map(String::from)
                    .collect()
            })
            .collect(),
        responses: serde_json::to_value(&responses).unwrap_or(Value::Null),
    };
    Ok((calibration, report))
}

/// A calibration estimated from simulated chessboard poses (camera frame), with its report and
/// the wall-clock seconds of its two steps.
struct PoseCalibration {
    calibration: Calibration,
    report: PoseCalibrationReport,
    simulate_seconds: f64,
    calibrate_seconds: f64,
}

/// Simulates `poses` chessboard poses into `OUT/calibration-poses` and calibrates the booth from
/// them (no progress display: this runs beside the scan, which shows its own).
fn calibrate_from_simulated_poses(
    opts: &DemoOptions,
    poses: usize,
) -> Result<PoseCalibration, DemoError> {
    let start = Instant::now();
    let pose_root = opts.out.join("calibration-poses");
    // The poses' truth (100 MB at the quick size) is read by nothing here: the estimate is
    // compared with the scan's truth.
    let pose_opts = SimulationOptions {
        truth: false,
        ..simulation_options(opts, SubjectKind::Chessboard)
    };
    let sim = simulate_calibration(&opts.booth, &pose_opts, poses, &pose_root, &NoProgress)?;
    let simulate_seconds = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let (calibration, report) = calibrate_from_poses(&sim.captures)?;
    Ok(PoseCalibration {
        calibration,
        report,
        simulate_seconds,
        calibrate_seconds: start.elapsed().as_secs_f64(),
    })
}

/// Errors of the estimated responses against the truth, percent.
fn response_errors(estimate: &Calibration, truth: &Calibration) -> Vec<ResponseErrors> {
    let rel = |a: f64, b: f64| 100.0 * (a - b) / b;
    estimate
        .projectors
        .iter()
        .zip(&truth.projectors)
        .filter_map(|(e, t)| {
            let (e, t) = (e.response?, t.response?);
            Some(ResponseErrors {
                gamma_rel_pct: rel(e.gamma, t.gamma),
                black_level_rel_pct: rel(e.black_level, t.black_level),
            })
        })
        .collect()
}

/// Mean of a field of the decoded projectors' truth comparisons.
fn mean_over_projectors(
    projectors: &[ProjectorDecodeReport],
    field: impl Fn(&mlsss_vision::geometry::gray_code::TruthComparison) -> f64,
) -> Option<f64> {
    let values: Vec<f64> = projectors
        .iter()
        .filter_map(|p| p.truth.as_ref().map(&field))
        .collect();
    (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
}

/// Callbacks of a running demonstration (progress on stderr in the CLI).
pub trait DemoProgress: Progress {
    /// A new step starts (simulation steps report through [`Progress`] as well).
    fn step(&self, name: &str);
}

/// Runs the demonstration.
pub fn run_demo(opts: &DemoOptions, progress: &dyn DemoProgress) -> Result<DemoOutcome, DemoError> {
    let total = Instant::now();
    let total_cpu = cpu_seconds();
    prepare_output(opts)?;
    let out = &opts.out;
    let mut timing = Timings::default();
    let capture = out.join("capture");
    let simulate_start = Instant::now();
    let simulate_cpu = cpu_seconds();
    let (sim, calibrated) = simulate(opts, &capture, progress, &mut timing)?;
    let (calib_source, calibration_report) =
        calibration_to_use(opts, &capture, calibrated, &mut timing)?;
    timing.add("simulate", simulate_start.elapsed().as_secs_f64());
    timing.add_cpu_since("simulate", simulate_cpu);

    progress.step("processing (decode .. fit)");
    let processed = out.join("processed");
    let report = process(opts, &capture, &processed, &calib_source)?;
    for (stage, seconds) in &report.timing_s {
        timing.add(stage, *seconds);
    }
    for (stage, seconds) in &report.timing_cpu_s {
        timing.add_cpu(stage, *seconds);
    }

    progress.step("relighting the held-out projector");
    let (relight, figures) = relight_held_out(opts, &capture, &processed, &mut timing)?;
    timing.add("total", total.elapsed().as_secs_f64());
    timing.add_cpu_since("total", total_cpu);

    let html = out.join(HTML_FILE);
    let info = DemoInfo {
        booth: opts.booth.name.clone(),
        camera: [opts.booth.camera.width, opts.booth.camera.height],
        subject: label(&opts.subject),
        skin: label(&opts.skin),
        seed: opts.seed,
        holdout_projector: opts.holdout,
        calibration: opts.calibration,
        monte_carlo: MonteCarloCounts {
            cached: sim.cache.hits,
            computed: sim.cache.misses,
        },
        out: out.clone(),
        exposure: Capture::open(&capture)?.manifest.exposure,
    };
    let demo = DemoReport {
        report_json: Some(out.join(REPORT_FILE)),
        report_html: Some(html.clone()),
        ..demo_report(info, calibration_report, report, relight, timing)
    };
    html_report::write_report(&html, &demo, Some(&figures), &processed)?;
    let path = out.join(REPORT_FILE);
    let text = serde_json::to_string_pretty(&demo).unwrap_or_default();
    mlsss_core::atomic_file::write_bytes_atomically(&path, text)
        .map_err(|source| DemoError::Io { path, source })?;
    Ok(DemoOutcome {
        report: demo,
        capture,
        processed,
    })
}

/// A value's JSON string (the snake-case name of a unit enum variant), empty otherwise.
fn label<T: Serialize>(value: &T) -> String {
    match serde_json::to_value(value) {
        Ok(Value::String(s)) => s,
        _ => String::new(),
    }
}

/// Simulates the scan into `capture` and, for an estimated calibration, the chessboard poses
/// and their calibration beside it.
fn simulate(
    opts: &DemoOptions,
    capture: &Path,
    progress: &dyn DemoProgress,
    timing: &mut Timings,
) -> Result<
    (
        mlsss_virtual_booth::SimulationReport,
        Option<PoseCalibration>,
    ),
    DemoError,
> {
    let scan_opts = simulation_options(opts, opts.subject);
    let scan = |progress: &dyn Progress| -> Result<_, DemoError> {
        let start = Instant::now();
        let sim = simulate_scan(&opts.booth, &scan_opts, capture, progress)?;
        Ok((sim, start.elapsed().as_secs_f64()))
    };
    let (sim, calibrated) = match opts.calibration {
        CalibrationMode::Truth => {
            progress.step("simulating the scan");
            (scan(progress)?, None)
        }
        CalibrationMode::Estimated { poses } => {
            // The chessboard poses and their calibration need nothing from the scan: they run
            // beside it and fill the cores whenever the scan leaves one idle (its Monte Carlo
            // tail, frame and truth writing). Only the scan reports progress.
            progress.step("simulating the scan (and calibrating beside it)");
            let (scan, calibrated) = rayon::join(
                || scan(progress),
                || calibrate_from_simulated_poses(opts, poses),
            );
            (scan?, Some(calibrated?))
        }
    };
    let (sim, scan_seconds) = sim;
    timing.add("simulate_scan", scan_seconds);
    Ok((sim, calibrated))
}

/// The calibration the pipeline uses: the truth, or the estimate re-expressed in the truth's
/// world frame and saved as `OUT/calibration.json`, with its errors against the truth.
fn calibration_to_use(
    opts: &DemoOptions,
    capture: &Path,
    calibrated: Option<PoseCalibration>,
    timing: &mut Timings,
) -> Result<(CalibrationSource, CalibrationReport), DemoError> {
    let Some(calibrated) = calibrated else {
        let report = CalibrationReport {
            source: "truth".into(),
            estimate: None,
            file: None,
            errors: None,
            response_errors: None,
        };
        return Ok((CalibrationSource::Truth, report));
    };
    let truth_dir = capture.join("truth");
    let truth_calibration = Calibration::load(&truth::calibration(&truth_dir))?;
    timing.add("simulate_calibration", calibrated.simulate_seconds);
    timing.add("calibrate", calibrated.calibrate_seconds);
    let aligned = align_world_frame(
        &calibrated.calibration,
        &truth_calibration.camera.extrinsics,
    );
    let path = opts.out.join("calibration.json");
    aligned.save(&path)?;
    let report = CalibrationReport {
        source: "estimated".into(),
        estimate: Some(calibrated.report),
        file: Some(path.clone()),
        errors: Some(calibration_errors(&aligned, &truth_calibration)?),
        response_errors: Some(response_errors(&aligned, &truth_calibration)),
    };
    Ok((CalibrationSource::File(path), report))
}

/// Runs the pipeline up to the fit, with the held-out projector left out of it.
fn process(
    opts: &DemoOptions,
    capture: &Path,
    processed: &Path,
    calib_source: &CalibrationSource,
) -> Result<PipelineReport, DemoError> {
    let mut pipeline = Pipeline::new(capture, processed, calib_source)?;
    let fit_params = FitParams {
        holdout: Some(opts.holdout),
        ..opts.fit.clone()
    };
    pipeline.set_params(
        "fit",
        serde_json::to_value(&fit_params).unwrap_or(Value::Null),
    );
    Ok(pipeline.run_until("fit")?)
}

/// Relights the held-out projector from the fitted model with every renderer, evaluates it
/// and (for a simulated capture) its back-scatter, whose plot goes to the processed folder.
fn relight_held_out(
    opts: &DemoOptions,
    capture: &Path,
    processed: &Path,
    timing: &mut Timings,
) -> Result<(RelightReport, html_report::RelightFigures), DemoError> {
    let scan = Capture::open(capture)?;
    // The capture's images need no model: read beside its loading (one core inflates it).
    let (model, images) = timing.time("eval", || {
        rayon::join(
            || SubsurfaceModel::load(&model_path(processed)),
            || HeldOutImages::read(&scan, opts.holdout),
        )
    });
    let (model, images) = (model?, images?);
    let mut renderers = vec![Baseline::Mlsss, Baseline::Homogeneous];
    if model.dipole.is_some() {
        renderers.push(Baseline::Dipole);
    }
    renderers.push(Baseline::Direct);
    let relight = timing.time("eval", || {
        evaluate_read_holdout(&scan, images, &model, &renderers, &opts.render)
    })?;
    timing.add("render", relight.render_seconds);
    let mut report = relight.report;
    if scan.truth_dir().is_some() {
        let found = timing.time("backscatter", || {
            evaluate_backscatter(&model, opts.holdout, &relight.slits)
        })?;
        if let Some(b) = found {
            b.plot.save_png(&processed.join(BACKSCATTER_PLOT))?;
            report.backscatter = Some(b.report);
        }
    }
    let figures = html_report::RelightFigures {
        images: relight.kept,
        mask: relight.mask,
    };
    Ok((report, figures))
}

/// The demonstration's report from its parts (without the file names).
fn demo_report(
    info: DemoInfo,
    calibration: CalibrationReport,
    report: PipelineReport,
    relight: RelightReport,
    timing: Timings,
) -> DemoReport {
    let decode = report.decode.map(|d| DecodeSummary {
        exact_fraction: mean_over_projectors(&d.projectors, |t| t.exact_fraction),
        valid_fraction: Some(d.valid_fraction),
        wrong_fraction: mean_over_projectors(&d.projectors, |t| t.wrong_fraction),
        projectors: d.projectors,
    });
    let separation = report.separate.map(|s| SeparationSummary {
        global_rel_rmse: s.truth.map(|t| t.global_rel_rmse),
        direct_rel_rmse: s.truth.map(|t| t.direct_rel_rmse),
        total_rel_rmse: s.truth.map(|t| t.total_rel_rmse),
        method: Some(s.method),
        nayar_global_rel_rmse: s.nayar_global_rel_rmse,
        nayar_direct_rel_rmse: s.nayar_direct_rel_rmse,
    });
    DemoReport {
        demo: Some(info),
        calibration: Some(calibration),
        decode,
        depth_rmse_mm: report
            .geometry
            .as_ref()
            .and_then(|g| g.truth.map(|t| t.depth_rmse_mm)),
        geometry: report.geometry,
        separation,
        normals: report.normals,
        relight: Some(relight),
        fit: report.fit,
        profiles: report.profiles,
        timing_s: timing.wall,
        timing_cpu_s: timing.cpu,
        peak_memory_mb: peak_memory_mb(),
        report_json: None,
        report_html: None,
    }
}
