//! The processing pipeline (DESIGN section 4): stages from named artefacts to named artefacts,
//! run on demand, cached on disk.
//!
//! ```text
//! OUT/
//!   report.json            the report object of the last run (what `--json` prints)
//!   <stage>/stage.json     cache record: key, the stage's report fragment, its run time
//!   <stage>/...            the stage's artefacts (EXR, PNG, PLY, JSON)
//! ```
//!
//! - A [`Stage`] names the stages whose artefacts it reads (`inputs`). [`Pipeline::run_until`]
//!   runs the requested stage and, first, only the stages it transitively needs.
//! - Cache: a stage's key hashes its name and version, its parameters (JSON), the capture's
//!   fingerprint (manifest + frame file sizes and modification times), the calibration when the
//!   stage uses one, and the keys of its inputs. A stage whose `stage.json` holds the same key is
//!   not run again; its report fragment is reused. Changing a parameter re-runs that stage and
//!   everything downstream of it.
//! - Hand-over: a stage may also leave an in-memory result for a later stage of the same run
//!   ([`StageContext::hand_over`], [`StageContext::take_handed_over`]), which then need not read it
//!   back from disk (e.g. the decoded slit frames, from `profiles` to `fit`). It is only taken
//!   when it was made under the key the pipeline holds for that stage in this run, and whatever
//!   is left is dropped when the run ends.
//! - Report: one JSON object. Each stage returns a fragment (a JSON object) stored under its name
//!   (e.g. `geometry.depth_rmse_mm`); run times go to `timing_s.<stage>` (wall) and
//!   `timing_cpu_s.<stage>` (CPU, all threads), reused stages are listed in `cached`.
//!
//! # How to add a stage
//! 1. Write the algorithm in its own library module (e.g. `mlsss_vision::photometry::nayar_separation`),
//!    independent of the pipeline.
//! 2. Add `pipeline/<stage>.rs` with `pub const STAGE: Stage = Stage { name, version, inputs,
//!    uses_calibration, run }`. `run(&StageContext)` reads its inputs' artefacts from
//!    `ctx.stage_dir(input)` (through loaders exported by the producing stage's file, e.g.
//!    [`decode_stage::load_coords`]), writes its own under `ctx.dir()`, and returns its report fragment.
//!    Parameters: `ctx.params::<MyParams>()?` (a `Serialize + Deserialize + Default` struct; the
//!    CLI fills them with [`Pipeline::set_params`]; keys given replace the defaults, and an
//!    unknown key or a mistyped value fails the run with [`PipelineError::Params`] naming the
//!    stage and the key). Bump `version` when the stage's output changes meaning.
//! 3. Register it in [`STAGES`] (after its inputs) and add a variant to the CLI's `--until` help.
//! 4. Errors: the stage's module has its own `thiserror` enum; return it boxed via
//!    [`StageFailure::new`].

pub mod decode_stage;
pub mod fit_stage;
pub mod geometry_stage;
pub mod line_plot;
pub mod normals_stage;
pub mod phase_clock;
pub mod profiles_stage;
pub mod projector_lights;
pub mod separate_stage;

use std::any::Any;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use mlsss_core::atomic_file::{FolderLock, LockError, write_bytes_atomically};
use mlsss_core::calibration::{Calibration, CalibrationError};
use mlsss_core::capture::{Capture, CaptureError, truth};
use mlsss_core::resources::{cpu_seconds, release_free_memory};

/// Every stage, in an order where inputs come first.
pub const STAGES: &[Stage] = &[
    decode_stage::STAGE,
    geometry_stage::STAGE,
    separate_stage::STAGE,
    normals_stage::STAGE,
    profiles_stage::STAGE,
    fit_stage::STAGE,
];

/// Name of the cache record in each stage folder.
pub const STAGE_RECORD: &str = "stage.json";
/// Name of the report file in the output folder.
pub const REPORT_FILE: &str = "report.json";

/// Errors of the pipeline itself (each stage's own errors arrive as [`StageFailure`]).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// `--until` names no registered stage.
    #[error("no stage named `{0}` (stages: {list})", list = stage_names().join(", "))]
    NoSuchStage(String),
    /// The capture folder could not be opened.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// The calibration could not be read.
    #[error(transparent)]
    Calibration(#[from] CalibrationError),
    /// `--calib truth` on a capture without ground truth.
    #[error("--calib truth: {0} has no truth/calibration.json (only simulated captures have one)")]
    NoTruthCalibration(PathBuf),
    /// A stage needs a calibration and none was given.
    #[error("stage `{0}` needs a calibration: pass --calib calib.json (or --calib truth)")]
    CalibrationRequired(&'static str),
    /// A file or folder of the output could not be written or read.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// Stage parameters do not fit the stage's parameter struct.
    #[error(transparent)]
    Params(#[from] ParamsError),
    /// A stage's report fragment does not fit the stage's report struct.
    #[error("report of stage `{stage}`: {source}")]
    Report {
        stage: &'static str,
        source: serde_json::Error,
    },
    /// Another run holds the output folder.
    #[error(transparent)]
    Lock(#[from] LockError),
    /// The output folder is the capture or inside it.
    #[error(
        "--out {out} and the capture {capture} overlap: the pipeline's artefacts would go into \
         the capture (and change its cache key); choose an --out outside it"
    )]
    OutputOverlapsCapture { out: PathBuf, capture: PathBuf },
    /// A stage failed.
    #[error("stage `{stage}` failed: {source}")]
    Stage {
        stage: &'static str,
        source: StageFailure,
    },
}

/// Parameters set for a stage ([`Pipeline::set_params`]) that the stage cannot take: an unknown
/// key, or a value of the wrong type or out of the type's range. Names the stage and the key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("parameters of stage `{stage}`: `{key}`: {message}")]
pub struct ParamsError {
    pub stage: &'static str,
    /// Dotted path of the offending key (`-` when the parameters are not a JSON object).
    pub key: String,
    pub message: String,
}

/// Reads the parameters `value` of `stage` into `P`: the keys given replace those of
/// `P::default()` (so a partial object is enough, also for flattened or foreign parameter
/// structs without `#[serde(default)]`); every key must be one of `P`'s and every value must fit
/// it, else a [`ParamsError`] naming the key.
pub fn parse_params<P>(stage: &'static str, value: &Value) -> Result<P, ParamsError>
where
    P: Serialize + serde::de::DeserializeOwned + Default,
{
    let error = |key: String, message: String| ParamsError {
        stage,
        key,
        message,
    };
    let Some(given) = value.as_object() else {
        return Err(error(
            "-".into(),
            format!("expected a JSON object of parameters, got {value}"),
        ));
    };
    let defaults = match serde_json::to_value(P::default()) {
        Ok(Value::Object(map)) => map,
        Ok(other) => {
            return Err(error(
                "-".into(),
                format!("defaults are not an object: {other}"),
            ));
        }
        Err(e) => return Err(error("-".into(), e.to_string())),
    };
    // Serde ignores unknown keys (and `deny_unknown_fields` does not combine with the flattened
    // structs some stages use): a key the defaults do not have is unknown.
    if let Some((key, known_here)) = unknown_key(value, &Value::Object(defaults.clone()), "") {
        return Err(error(
            key,
            format!("unknown parameter (known: {})", known_here.join(", ")),
        ));
    }
    let over_defaults = |keys: &mut dyn Iterator<Item = (&String, &Value)>| {
        let mut merged = defaults.clone();
        merged.extend(keys.map(|(k, v)| (k.clone(), v.clone())));
        serde_json::from_value::<P>(Value::Object(merged))
    };
    over_defaults(&mut given.iter()).map_err(|e| {
        // The key that fails on its own (over the defaults) is the culprit.
        let culprit = given
            .iter()
            .find(|kv| over_defaults(&mut std::iter::once(*kv)).is_err());
        let key = culprit.map_or_else(|| "-".to_owned(), |(k, _)| k.clone());
        error(key, e.to_string())
    })
}

/// The first key of `given` (dotted path from `prefix`) that `known` lacks, with the keys `known`
/// has at that level.
fn unknown_key(given: &Value, known: &Value, prefix: &str) -> Option<(String, Vec<String>)> {
    let (Value::Object(given), Value::Object(known)) = (given, known) else {
        return None;
    };
    for (k, v) in given {
        let path = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match known.get(k) {
            None => return Some((path, known.keys().cloned().collect())),
            Some(kv) => {
                if let Some(found) = unknown_key(v, kv, &path) {
                    return Some(found);
                }
            }
        }
    }
    None
}

/// A stage's own error, boxed so the pipeline does not depend on every stage's error type.
#[derive(Debug)]
pub struct StageFailure(Box<dyn std::error::Error + Send + Sync>);

impl StageFailure {
    pub fn new(err: impl std::error::Error + Send + Sync + 'static) -> Self {
        Self(Box::new(err))
    }
}

impl std::fmt::Display for StageFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Include the causes: stage errors wrap IO and image errors. Most already print their
        // source in their own message; a cause the text so far ends with is not repeated.
        let mut text = self.0.to_string();
        let mut source = self.0.source();
        while let Some(s) = source {
            let cause = s.to_string();
            if !text.ends_with(&cause) {
                text = format!("{text}: {cause}");
            }
            source = s.source();
        }
        f.write_str(&text)
    }
}

impl std::error::Error for StageFailure {}

impl StageFailure {
    /// The pipeline error for a failure of `stage`: [`PipelineError::Params`] when the stage
    /// refused its parameters, else [`PipelineError::Stage`].
    fn into_pipeline_error(self, stage: &'static str) -> PipelineError {
        match self.0.downcast::<ParamsError>() {
            Ok(params) => PipelineError::Params(*params),
            Err(other) => PipelineError::Stage {
                stage,
                source: StageFailure(other),
            },
        }
    }
}

/// One processing stage.
#[derive(Debug, Clone, Copy)]
pub struct Stage {
    pub name: &'static str,
    /// Bump when the meaning of the outputs changes: invalidates cached results.
    pub version: u32,
    /// Stages whose artefacts this stage reads.
    pub inputs: &'static [&'static str],
    /// True when the stage reads the calibration (it is then part of the cache key).
    pub uses_calibration: bool,
    /// Runs the stage: reads inputs, writes artefacts under `ctx.dir()`, returns its report
    /// fragment (a JSON object).
    pub run: fn(&StageContext) -> Result<Value, StageFailure>,
}

/// A stage's report as its JSON fragment (what [`Stage::run`] returns and the cache stores).
pub fn fragment<R: Serialize>(report: &R) -> Result<Value, StageFailure> {
    serde_json::to_value(report).map_err(StageFailure::new)
}

/// One artefact write for [`write_side_by_side`].
pub type ArtefactWrite<'a, E> = Box<dyn FnOnce() -> Result<(), E> + Send + 'a>;

/// Runs a stage's independent artefact writes side by side on rayon's threads: each file is
/// encoded and written mostly on one thread, so the stage waits for the longest, not the sum.
/// Every write runs even when one fails; the first error in list order is returned.
pub fn write_side_by_side<E: Send>(writes: Vec<ArtefactWrite<'_, E>>) -> Result<(), E> {
    use rayon::prelude::*;
    let results: Vec<Result<(), E>> = writes.into_par_iter().map(|write| write()).collect();
    results.into_iter().collect()
}

/// The report of a pipeline run (`OUT/report.json`, what `mlsss process --json` prints): each
/// stage's report under its name (only the stages that ran or came from the cache), run times
/// per stage, and the stages reused from the cache.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PipelineReport {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decode: Option<decode_stage::DecodeReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub geometry: Option<geometry_stage::GeometryReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub separate: Option<separate_stage::SeparateReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normals: Option<normals_stage::NormalsReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profiles: Option<profiles_stage::ProfilesReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fit: Option<fit_stage::FitReport>,
    /// Wall-clock seconds per stage (as recorded when it ran, also for cached stages).
    pub timing_s: BTreeMap<String, f64>,
    /// CPU seconds per stage (all threads), where the platform tells.
    pub timing_cpu_s: BTreeMap<String, f64>,
    /// Stages whose results were reused from the cache.
    pub cached: Vec<String>,
}

impl PipelineReport {
    /// Stores `fragment` as the typed report of `stage`.
    fn set(&mut self, stage: &str, fragment: Value) -> Result<(), serde_json::Error> {
        fn typed<T: serde::de::DeserializeOwned>(v: Value) -> Result<Option<T>, serde_json::Error> {
            serde_json::from_value(v).map(Some)
        }
        match stage {
            "decode" => self.decode = typed(fragment)?,
            "geometry" => self.geometry = typed(fragment)?,
            "separate" => self.separate = typed(fragment)?,
            "normals" => self.normals = typed(fragment)?,
            "profiles" => self.profiles = typed(fragment)?,
            "fit" => self.fit = typed(fragment)?,
            _ => {}
        }
        Ok(())
    }
}

/// Names of the registered stages, in order.
pub fn stage_names() -> Vec<&'static str> {
    STAGES.iter().map(|s| s.name).collect()
}

/// Where the calibration comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CalibrationSource {
    /// No calibration (stages that need one fail with a clear error).
    None,
    /// The simulator's true calibration, `CAPTURE/truth/calibration.json`.
    Truth,
    /// A calibration file.
    File(PathBuf),
}

/// What a running stage can see.
pub struct StageContext<'a> {
    pub capture: &'a Capture,
    pub calibration: Option<&'a Calibration>,
    /// The output folder (`OUT`).
    pub out: &'a Path,
    stage: &'static str,
    params: Option<&'a Value>,
    /// This stage's cache key and those of the stages run before it in this run.
    key: &'a str,
    keys: &'a BTreeMap<&'static str, String>,
    handed_over: &'a HandedOver,
}

/// In-memory results left by stages for later stages of the same run: stage name to (the
/// stage's key when it made it, the value).
#[derive(Default)]
struct HandedOver(Mutex<BTreeMap<&'static str, KeyedValue>>);

/// A handed-over value and the key of the stage run that made it.
type KeyedValue = (String, Box<dyn Any + Send>);

impl HandedOver {
    fn put(&self, stage: &'static str, key: &str, value: Box<dyn Any + Send>) {
        if let Ok(mut map) = self.0.lock() {
            map.insert(stage, (key.to_owned(), value));
        }
    }

    /// Removes and returns what `from` left, if it was made under `current_key` and is a `T`.
    fn take<T: Any>(&self, from: &str, current_key: Option<&String>) -> Option<T> {
        let mut map = self.0.lock().ok()?;
        if map.get(from).map(|(key, _)| key) != current_key {
            return None;
        }
        let (_, value) = map.remove(from)?;
        value.downcast::<T>().ok().map(|b| *b)
    }
}

impl StageContext<'_> {
    /// This stage's artefact folder, `OUT/<stage>/` (created before the stage runs).
    pub fn dir(&self) -> PathBuf {
        self.out.join(self.stage)
    }

    /// Another stage's artefact folder.
    pub fn stage_dir(&self, stage: &str) -> PathBuf {
        self.out.join(stage)
    }

    /// This stage's parameters (defaults when none were set). Parameters that do not fit `P`
    /// (unknown key, wrong type) are an error naming the stage and the key ([`parse_params`]),
    /// which the pipeline reports as [`PipelineError::Params`].
    pub fn params<P>(&self) -> Result<P, StageFailure>
    where
        P: Serialize + serde::de::DeserializeOwned + Default,
    {
        match self.params {
            None => Ok(P::default()),
            Some(v) => parse_params(self.stage, v).map_err(StageFailure::new),
        }
    }

    /// The calibration, or an error naming this stage.
    pub fn require_calibration(&self) -> Result<&Calibration, StageFailure> {
        self.calibration
            .ok_or_else(|| StageFailure::new(PipelineError::CalibrationRequired(self.stage)))
    }

    /// The capture's ground truth folder, if any.
    pub fn truth_dir(&self) -> Option<PathBuf> {
        self.capture.truth_dir()
    }

    /// Leaves `value` for a later stage of this run (see the module documentation); replaces
    /// what this stage left before.
    pub fn hand_over<T: Any + Send>(&self, value: T) {
        self.handed_over.put(self.stage, self.key, Box::new(value));
    }

    /// Takes what stage `from` left with [`StageContext::hand_over`] in this run, if it is a `T`
    /// made under the key the pipeline holds for `from` now. `None` otherwise (e.g. `from` came
    /// from the cache): the caller reads `from`'s artefacts instead.
    pub fn take_handed_over<T: Any + Send>(&self, from: &str) -> Option<T> {
        self.handed_over.take(from, self.keys.get(from))
    }
}

/// The cache record written beside a stage's artefacts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct StageRecord {
    key: String,
    report: Value,
    seconds: f64,
    /// CPU seconds (user + system, all threads) the stage used, where the platform tells.
    #[serde(default)]
    cpu_seconds: Option<f64>,
}

/// Progress callback: stage name, and true when its result is reused from the cache.
pub type StageObserver = Box<dyn Fn(&str, bool)>;

/// A pipeline over one capture, writing to one output folder.
pub struct Pipeline {
    capture: Capture,
    out: PathBuf,
    calibration: Option<Calibration>,
    calibration_hash: String,
    capture_fingerprint: String,
    params: BTreeMap<String, Value>,
    /// Called before each stage with its name and whether it comes from the cache (progress).
    pub on_stage: Option<StageObserver>,
}

impl Pipeline {
    /// Opens the capture and the calibration; nothing runs yet.
    pub fn new(
        capture_dir: &Path,
        out: &Path,
        calibration: &CalibrationSource,
    ) -> Result<Self, PipelineError> {
        let capture = Capture::open(capture_dir)?;
        let calib_path = match calibration {
            CalibrationSource::None => None,
            CalibrationSource::File(p) => Some(p.clone()),
            CalibrationSource::Truth => {
                let p = capture
                    .truth_dir()
                    .map(|t| truth::calibration(&t))
                    .filter(|p| p.is_file())
                    .ok_or_else(|| PipelineError::NoTruthCalibration(capture_dir.to_owned()))?;
                Some(p)
            }
        };
        let (calibration, calibration_hash) = match calib_path {
            None => (None, String::new()),
            Some(p) => {
                let c = Calibration::load(&p)?;
                let bytes = std::fs::read(&p).map_err(|source| PipelineError::Io {
                    path: p.clone(),
                    source,
                })?;
                (Some(c), blake3::hash(&bytes).to_hex().to_string())
            }
        };
        let capture_fingerprint = fingerprint(&capture)?;
        Ok(Self {
            capture,
            out: out.to_owned(),
            calibration,
            calibration_hash,
            capture_fingerprint,
            params: BTreeMap::new(),
            on_stage: None,
        })
    }

    /// Sets the parameters of a stage (JSON for its params struct); part of the cache key.
    pub fn set_params(&mut self, stage: &str, params: Value) {
        self.params.insert(stage.to_owned(), params);
    }

    pub fn capture(&self) -> &Capture {
        &self.capture
    }

    /// Runs `until` and every stage it needs (reusing cached results); returns the report.
    pub fn run_until(&self, until: &str) -> Result<PipelineReport, PipelineError> {
        let order = needed_stages(until)?;
        refuse_output_in_capture(&self.capture.root, &self.out)?;
        create_dir(&self.out)?;
        // One run at a time per output folder: two runs with different settings would
        // interleave their artefacts under one stage record.
        let _lock = FolderLock::acquire(&self.out)?;
        let mut report = PipelineReport::default();
        let mut keys: BTreeMap<&'static str, String> = BTreeMap::new();
        let handed_over = HandedOver::default();
        // Freed memory goes back to the system before the first stage and after the last, not
        // between stages: what a stage frees stays with the allocator for the next one, since
        // memory handed back comes again as fresh pages that the kernel faults in and zeroes one
        // by one. Handed back after every stage, the full-size `process --until fit` took
        // 1.63-1.66 million page faults and 7.4-8.3 s of system time; kept, 1.22-1.26 million and
        // 6.1-7.8 s (3 runs each, alternated; the total CPU time within its noise), peak 1.84 GB
        // either way (the fit stage hands memory back itself where its peak needs it), artefacts
        // byte-identical. Before the first stage: the demo simulated the capture just before, and
        // its freed memory, kept, raised the quick demo's peak from 1.06-1.14 to 1.19-1.25 GB.
        release_free_memory();
        for stage in order {
            let key = self.stage_key(stage, &keys);
            let dir = self.out.join(stage.name);
            let record_path = dir.join(STAGE_RECORD);
            // A cached record whose report no longer fits the stage's report struct is run again.
            let cached = read_record(&record_path)
                .filter(|r| r.key == key && report.set(stage.name, r.report.clone()).is_ok());
            if let Some(cb) = &self.on_stage {
                cb(stage.name, cached.is_some());
            }
            let record = match cached {
                Some(r) => {
                    report.cached.push(stage.name.to_owned());
                    r
                }
                None => {
                    let r = self.run_stage(stage, &dir, key.clone(), &keys, &handed_over)?;
                    report.set(stage.name, r.report.clone()).map_err(|source| {
                        PipelineError::Report {
                            stage: stage.name,
                            source,
                        }
                    })?;
                    r
                }
            };
            report.timing_s.insert(stage.name.into(), record.seconds);
            if let Some(c) = record.cpu_seconds {
                report.timing_cpu_s.insert(stage.name.into(), c);
            }
            keys.insert(stage.name, key);
        }
        // After the last: the caller's next work (the demo's evaluation renders).
        release_free_memory();
        let path = self.out.join(REPORT_FILE);
        write_json(&path, &serde_json::to_value(&report).unwrap_or(Value::Null))?;
        Ok(report)
    }

    fn run_stage(
        &self,
        stage: &Stage,
        dir: &Path,
        key: String,
        keys: &BTreeMap<&'static str, String>,
        handed_over: &HandedOver,
    ) -> Result<StageRecord, PipelineError> {
        if stage.uses_calibration && self.calibration.is_none() {
            return Err(PipelineError::CalibrationRequired(stage.name));
        }
        create_dir(dir)?;
        // A half-written record must not survive a failed run.
        let record_path = dir.join(STAGE_RECORD);
        let _ = std::fs::remove_file(&record_path);
        let ctx = StageContext {
            capture: &self.capture,
            calibration: self.calibration.as_ref(),
            out: &self.out,
            stage: stage.name,
            params: self.params.get(stage.name),
            key: &key,
            keys,
            handed_over,
        };
        let start = Instant::now();
        let cpu_start = cpu_seconds();
        let report = (stage.run)(&ctx).map_err(|source| source.into_pipeline_error(stage.name))?;
        let record = StageRecord {
            key,
            report,
            seconds: start.elapsed().as_secs_f64(),
            cpu_seconds: cpu_start.zip(cpu_seconds()).map(|(a, b)| b - a),
        };
        write_json(
            &record_path,
            &serde_json::to_value(&record).unwrap_or(Value::Null),
        )?;
        Ok(record)
    }

    fn stage_key(&self, stage: &Stage, keys: &BTreeMap<&str, String>) -> String {
        let mut h = blake3::Hasher::new();
        h.update(stage.name.as_bytes());
        h.update(&stage.version.to_le_bytes());
        h.update(self.capture_fingerprint.as_bytes());
        let params = self
            .params
            .get(stage.name)
            .map(|p| p.to_string())
            .unwrap_or_default();
        h.update(params.as_bytes());
        if stage.uses_calibration {
            h.update(self.calibration_hash.as_bytes());
        }
        for input in stage.inputs {
            h.update(keys.get(input).map(String::as_str).unwrap_or("").as_bytes());
        }
        h.finalize().to_hex().to_string()
    }
}

/// Refuses an output folder that is the capture or inside it.
fn refuse_output_in_capture(capture: &Path, out: &Path) -> Result<(), PipelineError> {
    let capture_full = absolute_clean(capture);
    let out_full = absolute_clean(out);
    if out_full.starts_with(&capture_full) {
        return Err(PipelineError::OutputOverlapsCapture {
            out: out.to_owned(),
            capture: capture.to_owned(),
        });
    }
    Ok(())
}

/// `path` made absolute with symbolic links resolved as far as it exists (an output may not exist
/// yet), so two spellings of one folder compare equal.
pub fn absolute_clean(path: &Path) -> PathBuf {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_owned());
    let mut existing = absolute.as_path();
    let mut rest = Vec::new();
    while !existing.exists() {
        match (existing.parent(), existing.file_name()) {
            (Some(parent), Some(name)) => {
                rest.push(name.to_owned());
                existing = parent;
            }
            _ => return absolute,
        }
    }
    let mut resolved = existing
        .canonicalize()
        .unwrap_or_else(|_| existing.to_owned());
    for name in rest.into_iter().rev() {
        resolved.push(name);
    }
    resolved
}

/// The stages `until` needs, inputs first, in registry order.
fn needed_stages(until: &str) -> Result<Vec<&'static Stage>, PipelineError> {
    let find = |name: &str| STAGES.iter().find(|s| s.name == name);
    let target = find(until).ok_or_else(|| PipelineError::NoSuchStage(until.to_owned()))?;
    let mut needed = vec![target.name];
    let mut frontier = vec![target];
    while let Some(stage) = frontier.pop() {
        for input in stage.inputs {
            if !needed.contains(input) {
                needed.push(input);
                frontier.extend(find(input));
            }
        }
    }
    Ok(STAGES.iter().filter(|s| needed.contains(&s.name)).collect())
}

/// Hash of the capture: manifest bytes plus name, size and modification time of every frame.
fn fingerprint(capture: &Capture) -> Result<String, PipelineError> {
    let io = |path: &Path| {
        let path = path.to_owned();
        move |source| PipelineError::Io { path, source }
    };
    let manifest = capture
        .root
        .join(mlsss_core::capture::folder::MANIFEST_FILE);
    let mut h = blake3::Hasher::new();
    h.update(&std::fs::read(&manifest).map_err(io(&manifest))?);
    let frames = capture.root.join("frames");
    if let Ok(entries) = std::fs::read_dir(&frames) {
        let mut files: Vec<_> = entries.filter_map(|e| e.ok()).collect();
        files.sort_by_key(|e| e.file_name());
        for e in files {
            let meta = e.metadata().map_err(io(&e.path()))?;
            h.update(e.file_name().as_encoded_bytes());
            h.update(&meta.len().to_le_bytes());
            if let Ok(t) = meta.modified()
                && let Ok(d) = t.duration_since(std::time::UNIX_EPOCH)
            {
                h.update(&d.as_nanos().to_le_bytes());
            }
        }
    }
    Ok(h.finalize().to_hex().to_string())
}

fn read_record(path: &Path) -> Option<StageRecord> {
    let text = std::fs::read_to_string(path).ok()?;
    serde_json::from_str(&text).ok()
}

fn create_dir(path: &Path) -> Result<(), PipelineError> {
    std::fs::create_dir_all(path).map_err(|source| PipelineError::Io {
        path: path.to_owned(),
        source,
    })
}

fn write_json(path: &Path, value: &Value) -> Result<(), PipelineError> {
    let text = serde_json::to_string_pretty(value).unwrap_or_default();
    write_bytes_atomically(path, text.as_bytes()).map_err(|source| PipelineError::Io {
        path: path.to_owned(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgb32FImage;
    use mlsss_core::booth::Booth;
    use mlsss_core::capture::FramePlan;
    use mlsss_core::capture::folder::{CaptureKind, CaptureManifest, CaptureWriter};
    use nalgebra::Point3;

    /// A capture of the plane z = `z0` (world) by a 2-projector quick booth, rendered exactly
    /// (point-sampled patterns, no noise), with the truth the simulator would write. Projector 1
    /// is switched off (all frames dark) when `dark_projector_1`.
    fn plane_capture(root: &Path, z0: f64, dark_projector_1: bool) -> PathBuf {
        let mut booth = Booth::builtin(true);
        booth.projectors.truncate(2);
        let cam = booth.camera_calibration();
        let calib = booth.calibration();
        let (w, h) = (cam.width, cam.height);
        let surface: Vec<Point3<f64>> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                let (o, d) = cam.ray(x as f64, y as f64);
                o + d * ((z0 - o.z) / d.z)
            })
            .collect();
        let coords: Vec<Vec<Option<(f64, f64)>>> = calib
            .projectors
            .iter()
            .map(|p| {
                surface
                    .iter()
                    .map(|s| {
                        p.device.project(s).filter(|q| {
                            q.x >= -0.5
                                && q.y >= -0.5
                                && q.x < p.device.width as f64 - 0.5
                                && q.y < p.device.height as f64 - 0.5
                        })
                    })
                    .map(|q| q.map(|q| (q.x, q.y)))
                    .collect()
            })
            .collect();
        let plan = FramePlan::scan(&booth.patterns, 2);
        let manifest = CaptureManifest::new(CaptureKind::Scan, booth, plan.clone());
        let target = root.join("plane");
        let writer = CaptureWriter::create(&target, manifest).unwrap();
        for f in &plan.frames {
            let k = f.projector.unwrap() as usize;
            let img = Rgb32FImage::from_fn(w, h, |x, y| {
                let i = (y * w + x) as usize;
                let lit = match coords[k][i] {
                    Some((u, v)) if !(dark_projector_1 && k == 1) => {
                        0.6 * f.pattern.value(u.round() as u32, v.round() as u32)
                    }
                    _ => 0.0,
                };
                image::Rgb([0.02 + lit; 3])
            });
            writer.write_frame(f.index, &img).unwrap();
        }
        let truth_dir = writer.staging_dir().join("truth");
        std::fs::create_dir_all(&truth_dir).unwrap();
        calib.save(&truth::calibration(&truth_dir)).unwrap();
        let depth = mlsss_core::imageio::GrayF32 {
            width: w,
            height: h,
            data: surface
                .iter()
                .map(|p| cam.extrinsics.world_to_device(p).z as f32)
                .collect(),
        };
        mlsss_core::imageio::write_exr_gray(&truth::depth(&truth_dir), &depth).unwrap();
        for (k, c) in coords.iter().enumerate() {
            let img = Rgb32FImage::from_fn(w, h, |x, y| match c[(y * w + x) as usize] {
                Some((u, v)) => image::Rgb([u as f32, v as f32, 1.0]),
                None => image::Rgb([0.0; 3]),
            });
            mlsss_core::imageio::write_exr_rgb(&truth::projector_coords(&truth_dir, k), &img)
                .unwrap();
        }
        writer.finish().unwrap()
    }

    #[test]
    fn a_handed_over_value_is_taken_once_and_only_under_the_current_key() {
        let handed = HandedOver::default();
        let (k1, k2) = (String::from("k1"), String::from("k2"));
        handed.put("profiles", "k1", Box::new(5u32));
        assert_eq!(
            handed.take::<u32>("profiles", Some(&k2)),
            None,
            "another run's key"
        );
        assert_eq!(handed.take::<u32>("profiles", None), None, "stage not run");
        assert_eq!(
            handed.take::<u64>("profiles", Some(&k1)),
            None,
            "another type"
        );
        handed.put("profiles", "k1", Box::new(5u32));
        assert_eq!(handed.take::<u32>("profiles", Some(&k1)), Some(5));
        assert_eq!(
            handed.take::<u32>("profiles", Some(&k1)),
            None,
            "taken once"
        );
    }

    #[test]
    fn side_by_side_writes_all_run_and_the_first_error_in_order_comes_back() {
        let ran = std::sync::atomic::AtomicUsize::new(0);
        let write = |result: Result<(), &'static str>| -> ArtefactWrite<'_, &'static str> {
            let ran = &ran;
            Box::new(move || {
                ran.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                result
            })
        };
        let writes = vec![
            write(Ok(())),
            write(Err("second")),
            write(Err("third")),
            write(Ok(())),
        ];
        assert_eq!(write_side_by_side(writes), Err("second"));
        assert_eq!(ran.load(std::sync::atomic::Ordering::SeqCst), 4);
        assert_eq!(
            write_side_by_side(vec![write(Ok(())), write(Ok(()))]),
            Ok(())
        );
    }

    #[test]
    fn decode_and_geometry_measure_a_plane_and_reuse_cached_stages() {
        let dir = tempfile::tempdir().unwrap();
        let capture = plane_capture(dir.path(), 5.0, false);
        let out = dir.path().join("out");
        let pipeline = Pipeline::new(&capture, &out, &CalibrationSource::Truth).unwrap();
        let report = pipeline.run_until("geometry").unwrap();
        for p in &report.decode.as_ref().unwrap().projectors {
            let t = p.truth.unwrap();
            assert!(p.counts.unwrap().valid_fraction > 0.8, "{p:?}");
            assert!(t.wrong_fraction < 0.002, "{p:?}");
            assert!(t.mean_abs_error_px < 0.2, "{p:?}");
        }
        let g = report.geometry.as_ref().unwrap();
        let depth = g.truth.unwrap();
        // Quick booth: ~0.6 mm projector pixels seen at ~40 degrees; sub-pixel codes give
        // sub-millimetre depth.
        assert!(depth.depth_rmse_mm < 0.5, "{g:?}");
        assert!(depth.depth_p95_abs_mm < 1.0, "{g:?}");
        assert!(depth.coverage > 0.8, "{g:?}");
        for f in ["depth.exr", "points.exr", "mesh.ply", "shaded.png"] {
            assert!(out.join("geometry").join(f).is_file(), "{f}");
        }
        // The points' plane fits: the plane z = 5 mm has the world normal along z (the fit turns
        // it towards the camera).
        let (w, h) = (
            pipeline.capture().manifest.booth.camera.width,
            pipeline.capture().manifest.booth.camera.height,
        );
        let normals = geometry_stage::load_point_normals(&out.join("geometry"), (w, h)).unwrap();
        let reliable: Vec<&[f32; 3]> = normals
            .normals
            .iter()
            .zip(&normals.reliable)
            .filter_map(|(n, r)| r.then_some(n))
            .collect();
        assert!(
            reliable.len() as f64 > 0.7 * f64::from(w * h),
            "{}",
            reliable.len()
        );
        let mut angles: Vec<f64> = reliable
            .iter()
            .map(|n| f64::from(n[2].abs()).min(1.0).acos().to_degrees())
            .collect();
        angles.sort_by(f64::total_cmp);
        let mean = angles.iter().sum::<f64>() / angles.len() as f64;
        let p95 = angles[angles.len() * 95 / 100];
        // Measured 2.3 and 5.3 deg: the decoded depth's steps (RMSE under 0.5 mm) over a window
        // of sigma 1.5 px.
        assert!(mean < 3.0 && p95 < 7.0, "mean {mean} deg, p95 {p95} deg");
        assert!(out.join("decode/proj1_codes.png").is_file());
        assert!(report.timing_s["decode"] > 0.0);
        assert!(report.cached.is_empty());
        // What report.json holds is the typed report (serde_json's text parsing may differ from
        // the written float in the last bit: compared loosely).
        let written: PipelineReport =
            serde_json::from_str(&std::fs::read_to_string(out.join(REPORT_FILE)).unwrap()).unwrap();
        let written_depth = written.geometry.as_ref().and_then(|g| g.truth).unwrap();
        assert!((written_depth.depth_rmse_mm - depth.depth_rmse_mm).abs() < 1e-12);
        assert_eq!(written.decode.map(|d| d.projectors.len()), Some(2));

        // Same inputs: both stages come from the cache. New geometry parameters: only geometry.
        let again = pipeline.run_until("geometry").unwrap();
        assert_eq!(again.cached, ["decode", "geometry"]);
        assert_eq!(again.geometry, report.geometry);
        let mut pipeline = pipeline;
        pipeline.set_params("geometry", serde_json::json!({ "max_edge_mm": 2.0 }));
        let third = pipeline.run_until("geometry").unwrap();
        assert_eq!(third.cached, ["decode"]);

        // Parameters the stage cannot take stop the run, naming the stage and the key, instead
        // of running it with defaults.
        pipeline.set_params("geometry", serde_json::json!({ "max_edge_mm": "long" }));
        let err = pipeline.run_until("geometry").unwrap_err();
        assert!(
            matches!(&err, PipelineError::Params(p) if p.stage == "geometry" && p.key == "max_edge_mm"),
            "{err:?}"
        );
        assert!(err.to_string().contains("`geometry`"), "{err}");
        pipeline.set_params("geometry", serde_json::json!({ "max_edge": 2.0 }));
        let err = pipeline.run_until("geometry").unwrap_err();
        assert!(err.to_string().contains("`max_edge`"), "{err}");
        assert!(
            err.to_string().contains("max_edge_mm"),
            "lists the known keys: {err}"
        );
    }

    #[test]
    fn the_lobe_separation_without_the_slit_sweep_gives_the_split_with_it() {
        // The lobe replaces every direct part the slit sweep's leak corrects, so skipping the
        // sweep (the default) must not change the images, only drop the leak's counters.
        let dir = tempfile::tempdir().unwrap();
        let capture = plane_capture(dir.path(), 5.0, false);
        let run = |leak_with_lobe: bool, out: &str| {
            let out = dir.path().join(out);
            let mut pipeline = Pipeline::new(&capture, &out, &CalibrationSource::Truth).unwrap();
            let params = separate_stage::SeparateParams {
                leak_with_lobe,
                ..Default::default()
            };
            pipeline.set_params("separate", serde_json::to_value(&params).unwrap());
            let report = pipeline.run_until("separate").unwrap();
            (report.separate.unwrap(), out.join("separate"))
        };
        let (without, dir_without) = run(false, "without");
        let (with, dir_with) = run(true, "with");
        assert!(without.lobe.is_some() && with.lobe.is_some());
        assert!(without.projectors.iter().all(|p| p.leak.is_none()));
        assert!(with.projectors.iter().all(|p| p.leak.is_some()));
        for k in 0..2 {
            for path in [separate_stage::direct_path, separate_stage::global_path] {
                let a = mlsss_core::imageio::read_exr_rgb(&path(&dir_without, k)).unwrap();
                let b = mlsss_core::imageio::read_exr_rgb(&path(&dir_with, k)).unwrap();
                for (x, y) in a.iter().zip(b.iter()) {
                    assert!((x - y).abs() <= 1e-6 * x.abs().max(1e-3), "{x} against {y}");
                }
            }
        }
    }

    #[test]
    fn parameters_name_the_stage_and_the_offending_key() {
        use fit_stage::FitParams;
        let ok: FitParams = parse_params("fit", &serde_json::json!({ "block": 3 })).unwrap();
        assert_eq!(
            ok,
            FitParams {
                block: 3,
                ..FitParams::default()
            }
        );
        let err = parse_params::<FitParams>("fit", &serde_json::json!({ "blok": 3 })).unwrap_err();
        assert_eq!((err.stage, err.key.as_str()), ("fit", "blok"));
        assert!(err.message.contains("unknown parameter"), "{err}");
        let err = parse_params::<FitParams>(
            "fit",
            &serde_json::json!({ "components": 4, "block": "six" }),
        )
        .unwrap_err();
        assert_eq!(err.key, "block", "{err}");
        assert!(err.message.contains("invalid type"), "{err}");
        let err =
            parse_params::<FitParams>("fit", &serde_json::json!({ "em": "bogus" })).unwrap_err();
        assert_eq!(err.key, "em", "{err}");
        // Flattened structs (geometry's triangulation parameters) are known keys too.
        let g = geometry_stage::GeometryParams::default();
        let mut v = serde_json::to_value(&g).unwrap();
        parse_params::<geometry_stage::GeometryParams>("geometry", &v).unwrap();
        v["typo"] = serde_json::json!(1);
        let err = parse_params::<geometry_stage::GeometryParams>("geometry", &v).unwrap_err();
        assert_eq!(err.key, "typo");
        let err = parse_params::<FitParams>("fit", &Value::Null).unwrap_err();
        assert_eq!(err.key, "-");
    }

    #[test]
    fn a_dark_projector_is_skipped_and_reported_and_unknown_stages_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let capture = plane_capture(dir.path(), 0.0, true);
        let out = dir.path().join("out");
        let pipeline = Pipeline::new(&capture, &out, &CalibrationSource::None).unwrap();
        let report = pipeline.run_until("decode").unwrap();
        let decode = report.decode.as_ref().unwrap();
        let p1 = &decode.projectors[1];
        assert!(
            p1.skipped
                .as_deref()
                .unwrap()
                .contains("no camera pixel is lit"),
            "{p1:?}"
        );
        assert!(decode.projectors[0].counts.unwrap().valid_fraction > 0.8);
        assert!(report.geometry.is_none(), "only what was asked for runs");

        let err = pipeline.run_until("geometry").unwrap_err();
        assert!(err.to_string().contains("--calib"), "{err}");
        let err = pipeline.run_until("normals2").unwrap_err();
        assert!(err.to_string().contains("decode, geometry"), "{err}");
    }
}
