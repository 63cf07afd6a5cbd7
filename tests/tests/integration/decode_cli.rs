//! `mlsss decode` / `mlsss process` from the command line: bad input gives a clear error and a
//! failing exit status, never a panic.

use mlsss_tests::mlsss;

fn opencv_folder(frames: usize) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let png = [
        0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, // signature only: never decoded
    ];
    for i in 0..frames {
        std::fs::write(dir.path().join(format!("graycode_{i:02}.png")), png).unwrap();
    }
    dir
}

#[test]
fn opencv_layout_with_a_missing_frame_names_the_count_and_the_fix() {
    let dir = opencv_folder(41);
    let out = dir.path().join("out");
    let result = mlsss()
        .args([
            "decode",
            "--layout",
            "opencv",
            "--projector",
            "1024x768",
            "--out",
        ])
        .arg(&out)
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!result.status.success());
    let err = String::from_utf8_lossy(&result.stderr);
    assert!(err.contains("found 41") && err.contains("has 42"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn opencv_layout_needs_the_projector_size_and_a_valid_one() {
    let dir = opencv_folder(42);
    let run = |extra: &[&str]| {
        mlsss()
            .args(["decode", "--layout", "opencv", "--out", "unused"])
            .args(extra)
            .arg(dir.path())
            .output()
            .unwrap()
    };
    let missing = run(&[]);
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("--projector"));
    let bad = run(&["--projector", "1024by768"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("WIDTHxHEIGHT"));
    // Undecodable PNG content is an error naming the file.
    let corrupt = run(&["--projector", "1024x768"]);
    assert!(!corrupt.status.success());
    let err = String::from_utf8_lossy(&corrupt.stderr);
    assert!(
        err.contains("graycode_") && !err.contains("panicked"),
        "{err}"
    );
}

#[test]
fn process_without_a_capture_manifest_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let result = mlsss()
        .args(["process", "--calib", "truth", "--out"])
        .arg(dir.path().join("out"))
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!result.status.success());
    let err = String::from_utf8_lossy(&result.stderr);
    assert!(err.contains("capture.json"), "{err}");
}
