//! Helpers shared by the integration tests.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Mutex, OnceLock};

/// Path of the `mlsss` binary built beside the test executable (`cargo test --workspace` builds it;
/// `CARGO_BIN_EXE_*` is only set for binaries of the test's own package).
pub fn mlsss_bin() -> PathBuf {
    let bin = profile_dir().join(format!("mlsss{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.exists(),
        "{} not found: run the tests with `cargo test --workspace` so the binary is built",
        bin.display()
    );
    bin
}

/// `target/<profile>` of the running test executable.
fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/integration-<hash> -> target/<profile>
    exe.parent()
        .and_then(|deps| deps.parent())
        .expect("test executable lives in target/<profile>/deps")
        .to_owned()
}

/// A `Command` running `mlsss`.
pub fn mlsss() -> Command {
    Command::new(mlsss_bin())
}

/// Monte Carlo response cache shared by every test run (responses are content-hashed, so a
/// stale entry can never be used for other inputs): `target/mlsss-test-cache`.
pub fn mc_cache_dir() -> PathBuf {
    profile_dir()
        .parent()
        .map(|target| target.join("mlsss-test-cache"))
        .expect("target directory")
}

/// Environment variable that keeps the scratch directory after the test process exits.
pub const KEEP_OUTPUT_VAR: &str = "MLSSS_KEEP_TEST_OUTPUT";

static SCRATCH_DIR: OnceLock<PathBuf> = OnceLock::new();

/// A fresh scratch directory for this test process (`$TMPDIR/mlsss-tests-<pid>`), removed when the
/// process exits unless `MLSSS_KEEP_TEST_OUTPUT` is set: the shared scans in it take about half a
/// gigabyte, and CI machines can be short of disk.
pub fn scratch_dir() -> &'static Path {
    SCRATCH_DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("mlsss-tests-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("create scratch dir");
        if std::env::var_os(KEEP_OUTPUT_VAR).is_none() {
            remove_at_exit();
        }
        dir
    })
}

/// Registers [`remove_scratch_dir`] with the C runtime: the test harness ends the process with
/// `exit` (after the last test, passed or failed), which runs it. Rust statics are never dropped.
fn remove_at_exit() {
    unsafe extern "C" {
        fn atexit(callback: extern "C" fn()) -> std::ffi::c_int;
    }
    // SAFETY: `atexit` is the C standard library's; the callback takes no arguments, does not
    // unwind (it ignores every error) and touches only a `OnceLock` that is set by then.
    let registered = unsafe { atexit(remove_scratch_dir) };
    assert_eq!(registered, 0, "atexit refused the scratch cleanup");
}

extern "C" fn remove_scratch_dir() {
    if let Some(dir) = SCRATCH_DIR.get() {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// One test's own output folder inside [`scratch_dir`], removed when the test passes and kept when
/// it fails (dropped while panicking), so a passing suite holds only the shared scans at once.
pub struct TestDir(PathBuf);

impl TestDir {
    /// `scratch_dir()/name`; the folder itself is not created (most commands refuse an existing one).
    pub fn new(name: &str) -> Self {
        Self(scratch_dir().join(name))
    }

    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TestDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// Runs `cmd`, fails the test with its stderr unless it succeeds, and returns the one JSON object
/// it printed on stdout (the `--json` contract).
pub fn run_json(cmd: &mut Command) -> serde_json::Value {
    let output = cmd.output().expect("run the command");
    assert!(
        output.status.success(),
        "{cmd:?} failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("--json prints one JSON object on stdout")
}

/// Runs `mlsss simulate` with `args` into `out` (quick booth shrunk by `scale_down`, small photon
/// counts unless `args` set `--photons`, shared Monte Carlo cache); panics with the tool's stderr on failure. Returns the
/// `--json` report.
pub fn simulate(out: &Path, scale_down: u32, args: &[&str]) -> serde_json::Value {
    let mut cmd = mlsss();
    cmd.args(["simulate", "--quick", "--json"]);
    if !args.contains(&"--photons") {
        cmd.args(["--photons", "4000"]);
    }
    cmd.args(["--scale-down", &scale_down.to_string()])
        .arg("--cache")
        .arg(mc_cache_dir())
        .arg("--out")
        .arg(out)
        .args(args);
    run_json(&mut cmd)
}

/// A simulated scan of `subject` (`plane`, `sphere`, `head`) with `seed`, made once per test
/// binary run and shared by every test that asks for the same pair: the `--quick` booth shrunk
/// 2x (230x171 camera, 128x96 projectors, 7-bit Gray code), all 4 projectors, full truth.
pub fn quick_capture(subject: &str, seed: u64) -> PathBuf {
    type Made = Vec<((String, u64), PathBuf)>;
    static CAPTURES: OnceLock<Mutex<Made>> = OnceLock::new();
    let captures = CAPTURES.get_or_init(|| Mutex::new(Vec::new()));
    // Holding the lock while simulating makes concurrent tests wait for one simulation.
    let mut done = captures.lock().unwrap_or_else(|e| e.into_inner());
    let key = (subject.to_owned(), seed);
    if let Some((_, path)) = done.iter().find(|(k, _)| *k == key) {
        return path.clone();
    }
    let out = scratch_dir().join(format!("scan-{subject}-{seed}"));
    simulate(
        &out,
        2,
        &["--subject", subject, "--seed", &seed.to_string()],
    );
    done.push((key, out.clone()));
    out
}

/// Chessboard poses in the shared calibration set: tests that need fewer use the first ones (the
/// poses depend only on the seed and the pose index).
pub const CALIBRATION_POSES: usize = 6;

/// Chessboard calibration captures (`poses` poses, all 4 projectors) of the `--quick` booth
/// shrunk 2x, made once per test binary run; returns the folder holding `pose00`, `pose01`, ...
pub fn calibration_captures(poses: usize) -> PathBuf {
    static CAPTURES: OnceLock<Mutex<Vec<(usize, PathBuf)>>> = OnceLock::new();
    let captures = CAPTURES.get_or_init(|| Mutex::new(Vec::new()));
    let mut done = captures.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((_, path)) = done.iter().find(|(k, _)| *k == poses) {
        return path.clone();
    }
    let out = scratch_dir().join(format!("calibration-{poses}"));
    simulate(
        &out,
        2,
        &[
            "--subject",
            "chessboard",
            "--calibration",
            "--poses",
            &poses.to_string(),
            "--seed",
            "1",
        ],
    );
    done.push((poses, out.clone()));
    out
}

/// `mlsss calibrate` of all [`CALIBRATION_POSES`] shared calibration captures (k3 fixed; the board
/// is the one the simulated captures record), made once per test binary run; returns the
/// calibration file (in the camera's frame, as from a real booth) and the `--json` report.
pub fn estimated_calibration() -> &'static (PathBuf, serde_json::Value) {
    static CALIBRATION: OnceLock<(PathBuf, serde_json::Value)> = OnceLock::new();
    CALIBRATION.get_or_init(|| {
        let root = calibration_captures(CALIBRATION_POSES);
        let out = scratch_dir().join(format!("calibration-{CALIBRATION_POSES}.json"));
        let report = run_json(
            mlsss()
                .arg("calibrate")
                .args((0..CALIBRATION_POSES).map(|p| root.join(format!("pose{p:02}"))))
                .args(["--fix-k3", "--json", "--out"])
                .arg(&out),
        );
        (out, report)
    })
}

/// The shared quick head capture processed up to the fit with projector 3 held out (once per
/// test binary run; few components, 8x8 tiles); returns the output folder and the report.
/// `--direct none` (the default before `auto`): on this tiny light-skin scene `auto` removes
/// some separated direct light and the per-pixel model then ties the homogeneous one under
/// white light (0.1431 against 0.1427, i18b 6aacf72), which the fit tests' margin does not
/// allow; the tiny type-VI demo test runs the `auto` default end to end.
pub fn fitted_head() -> &'static (PathBuf, serde_json::Value) {
    static FITTED: OnceLock<(PathBuf, serde_json::Value)> = OnceLock::new();
    FITTED.get_or_init(|| {
        let capture = quick_capture("head", 1);
        let out = scratch_dir().join("fit-head");
        let report = run_json(
            mlsss()
                .arg("process")
                .arg(&capture)
                .args(["--calib", "truth", "--until", "fit", "--json"])
                .args(["--components", "4", "--block", "8"])
                .args([
                    "--holdout",
                    "3",
                    "--heldout-check",
                    "--compare-slit-variants",
                ])
                .args(["--direct", "none"])
                .arg("--out")
                .arg(&out),
        );
        (out, report)
    })
}
