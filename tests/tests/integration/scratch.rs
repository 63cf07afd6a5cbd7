//! The test scratch space cleans up after itself (regression: a CI run died with "No space left on
//! device" while every test process left its half-gigabyte of scans in `/tmp`).

use mlsss_tests::{KEEP_OUTPUT_VAR, TestDir, scratch_dir};
use std::process::Command;

/// Set in the child test process of [`scratch_dir_is_removed_when_the_test_process_exits`].
const PROBE_VAR: &str = "MLSSS_SCRATCH_PROBE";

/// The contract of [`scratch_dir`]: `$TMPDIR/mlsss-tests-<pid>`, a directory this process can
/// write, the same one on every call. In the child of
/// [`scratch_dir_is_removed_when_the_test_process_exits`] it also leaves a file in it and prints
/// its path; in the parent it removes the file again.
#[test]
fn scratch_probe() {
    let dir = scratch_dir();
    let expected = std::env::temp_dir().join(format!("mlsss-tests-{}", std::process::id()));
    assert_eq!(dir, expected);
    assert!(dir.is_dir(), "{} is not a directory", dir.display());
    assert_eq!(scratch_dir(), dir, "one scratch directory per process");
    let file = dir.join("probe.bin");
    std::fs::write(&file, vec![0u8; 4096]).unwrap();
    assert_eq!(std::fs::metadata(&file).unwrap().len(), 4096);
    if std::env::var_os(PROBE_VAR).is_none() {
        std::fs::remove_file(&file).unwrap();
        return;
    }
    println!("scratch={}", dir.display());
}

#[test]
fn scratch_dir_is_removed_when_the_test_process_exits() {
    let exe = std::env::current_exe().unwrap();
    let output = Command::new(exe)
        .args([
            "--exact",
            "scratch::scratch_probe",
            "--nocapture",
            "--test-threads",
            "1",
        ])
        .env(PROBE_VAR, "1")
        .env_remove(KEEP_OUTPUT_VAR)
        .output()
        .unwrap();
    assert!(output.status.success(), "{output:?}");
    let stdout = String::from_utf8_lossy(&output.stdout);
    // The harness prints "test scratch::scratch_probe ... " on the same line.
    let dir = stdout
        .split_once("scratch=")
        .and_then(|(_, rest)| rest.lines().next())
        .unwrap_or_else(|| panic!("the probe printed no scratch path: {stdout}"));
    assert!(dir.contains("mlsss-tests-"), "{dir}");
    assert!(
        !std::path::Path::new(dir).exists(),
        "{dir} outlived its test process"
    );
}

#[test]
fn a_passing_test_removes_its_own_folder_and_a_failing_one_keeps_it() {
    let passed = TestDir::new("passing-test");
    std::fs::create_dir_all(passed.path()).unwrap();
    let passed_path = passed.path().to_owned();
    drop(passed);
    assert!(!passed_path.exists());

    let failed_path = std::thread::spawn(|| {
        let failed = TestDir::new("failing-test");
        std::fs::create_dir_all(failed.path()).unwrap();
        let path = failed.path().to_owned();
        std::panic::panic_any(path)
    })
    .join()
    .expect_err("the thread panics")
    .downcast::<std::path::PathBuf>()
    .unwrap();
    assert!(failed_path.is_dir(), "kept for inspection");
    std::fs::remove_dir_all(*failed_path).unwrap();
}
