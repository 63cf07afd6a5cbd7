//! Photometry on simulated captures: `mlsss process --until normals` (separation and near-light
//! photometric stereo against the simulator's truth) and `mlsss response` (projector gamma and
//! black level against the true calibration).

use mlsss_tests::{CALIBRATION_POSES, calibration_captures, mlsss, quick_capture, run_json};

#[test]
fn process_until_normals_reports_separation_and_normal_errors_on_a_head() {
    let capture = quick_capture("head", 1);
    let out = tempfile::tempdir().unwrap();
    let report = run_json(
        mlsss()
            .arg("process")
            .arg(&capture)
            .args(["--calib", "truth", "--until", "normals", "--json", "--out"])
            .arg(out.path()),
    );
    let sep = &report["separate"];
    // Direct + global reproduce the truth's total once the stray black light is removed.
    assert!(sep["total_rel_rmse"].as_f64().unwrap() < 0.05, "{sep}");
    assert!(sep["direct_rel_rmse"].as_f64().unwrap().is_finite());
    assert!(sep["global_rel_rmse"].as_f64().unwrap() < 1.0, "{sep}");
    let normals = &report["normals"];
    let mean = normals["mean_angular_error_deg"].as_f64().unwrap();
    let median = normals["median_angular_error_deg"].as_f64().unwrap();
    let p95 = normals["p95_angular_error_deg"].as_f64().unwrap();
    assert!(mean < 6.0 && median < 5.0 && p95 < 12.0, "{normals}");
    assert!(normals["coverage"].as_f64().unwrap() > 0.8, "{normals}");
    assert!(out.path().join("separate/separation.png").is_file());
    assert!(out.path().join("normals/normals.exr").is_file());
}

#[test]
fn response_recovers_gamma_and_black_level_of_the_virtual_booth() {
    let root = calibration_captures(CALIBRATION_POSES);
    let truth: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root.join("pose00/truth/calibration.json")).unwrap(),
    )
    .unwrap();
    let out = tempfile::tempdir().unwrap();
    let calib = out.path().join("calib.json");
    std::fs::copy(root.join("pose00/truth/calibration.json"), &calib).unwrap();
    let report = run_json(
        mlsss()
            .arg("response")
            .args((0..2).map(|p| root.join(format!("pose{p:02}"))))
            .arg("--calib")
            .arg(&calib)
            .arg("--json"),
    );
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
    for k in 0..4 {
        let t = &truth["projectors"][k]["response"];
        let fit = &report["projectors"][k];
        let rel = |key: &str| {
            (fit[key].as_f64().unwrap() - t[key].as_f64().unwrap()).abs() / t[key].as_f64().unwrap()
        };
        assert!(rel("gamma") < 0.02, "projector {k}: {fit} vs {t}");
        assert!(rel("black_level") < 0.10, "projector {k}: {fit} vs {t}");
        assert_eq!(written["projectors"][k]["response"]["gamma"], fit["gamma"]);
    }
}
