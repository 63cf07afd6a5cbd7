//! `mlsss booth`: the built-in booths and a broken booth file.

use mlsss_tests::mlsss;

#[test]
fn default_booth_has_268_frames_in_53_6_seconds() {
    let out = mlsss().args(["booth", "--json"]).output().unwrap();
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["frames"], 268);
    assert!((v["capture_seconds"].as_f64().unwrap() - 53.6).abs() < 1e-9);
}

#[test]
fn broken_booth_file_names_file_line_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken.toml");
    let text = include_str!("../../../hardware/booth.toml").replace("bit_depth = 12\n", "");
    std::fs::write(&path, text).unwrap();
    let out = mlsss()
        .args(["booth", "--file"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("broken.toml:"), "{err}");
    assert!(err.contains("bit_depth"), "{err}");
}
