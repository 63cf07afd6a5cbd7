//! `mlsss ps-scene` + `mlsss normals`: photometric stereo on a generated image set with known
//! normals, shadows and highlights, against every truth format.

use std::path::Path;

use mlsss_tests::mlsss;

fn normals_json(dir: &Path, extra: &[&str]) -> serde_json::Value {
    let out = mlsss()
        .arg("normals")
        .arg("--images")
        .arg(dir)
        .arg("--lights")
        .arg(dir.join("light_directions.txt"))
        .arg("--intensities")
        .arg(dir.join("light_intensities.txt"))
        .arg("--mask")
        .arg(dir.join("mask.png"))
        .arg("--out")
        .arg(dir.join("estimate.exr"))
        .arg("--json")
        .args(extra)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn robust_normals_beat_least_squares_on_a_generated_set() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("set");
    let out = mlsss()
        .args(["ps-scene", "--size", "64", "--lights", "10", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let mut means = Vec::new();
    for truth in ["normal.exr", "normal.png", "Normal_gt.mat"] {
        let truth = dir.join(truth);
        let robust = normals_json(&dir, &["--truth", truth.to_str().unwrap()]);
        means.push(robust["mean_angular_error_deg"].as_f64().unwrap());
        assert!(robust["pixels"].as_u64().unwrap() > 1500);
        let used = robust["lights_used_mean"].as_f64().unwrap();
        assert!(
            used > 5.0 && used < 10.0,
            "shadows and highlights dropped: {used}"
        );
    }
    // Same answer whatever the truth encoding (PNG is 16-bit quantised).
    assert!(
        means.iter().all(|m| (m - means[0]).abs() < 0.01),
        "{means:?}"
    );
    assert!(means[0] < 2.0, "robust mean error {}", means[0]);

    let truth = dir.join("Normal_gt.mat");
    let ls = normals_json(
        &dir,
        &[
            "--truth",
            truth.to_str().unwrap(),
            "--method",
            "least-squares",
        ],
    );
    let ls_mean = ls["mean_angular_error_deg"].as_f64().unwrap();
    assert!(
        ls_mean > 3.0 * means[0],
        "least squares {ls_mean} vs robust {}",
        means[0]
    );
    assert_eq!(ls["lights_used_mean"].as_f64().unwrap(), 10.0);

    // Four of the lights, like the booth.
    let four = normals_json(
        &dir,
        &["--truth", truth.to_str().unwrap(), "--select", "1,4,7,10"],
    );
    assert_eq!(four["images"], 4);
    assert!(four["median_angular_error_deg"].as_f64().unwrap() < 1.0);
    assert!(four["flagged"]["too_few_lights"].as_u64().unwrap() > 0);
}

/// Runs `mlsss normals` on an image set with an explicit lights file.
fn normals_with_lights_file(
    images: &std::path::Path,
    lights: &std::path::Path,
    out: &std::path::Path,
) -> std::process::Output {
    mlsss()
        .arg("normals")
        .arg("--images")
        .arg(images)
        .arg("--lights")
        .arg(lights)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn mismatched_lights_file_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("set");
    let ok = mlsss()
        .args(["ps-scene", "--size", "16", "--lights", "4", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(ok.status.success());
    let lights = tmp.path().join("lights.txt");
    std::fs::write(&lights, "0 0 1\n0.5 0 1\n0 0.5 1\n").unwrap();
    let out = normals_with_lights_file(&dir, &lights, &tmp.path().join("n.exr"));
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("lights.txt")
            && err.contains("3 light directions")
            && err.contains("4 images"),
        "{err}"
    );

    std::fs::write(&lights, "0 0 1\n0.5 zero 1\n0 0.5 1\n1 1 1\n").unwrap();
    let out = normals_with_lights_file(&dir, &lights, &tmp.path().join("n.exr"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("line 2") && err.contains("'zero'"),
        "{err}"
    );
}
