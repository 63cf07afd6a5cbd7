//! Photometry on simulated captures: `mlsss process --until normals` (separation and near-light
//! photometric stereo against the simulator's truth) and `mlsss response` (projector gamma and
//! black level against the true calibration).

use std::path::Path;

use mlsss_tests::{
    CALIBRATION_POSES, calibration_captures, estimated_calibration, mlsss, quick_capture, run_json,
};

/// `mlsss process CAPTURE --calib CALIB --until normals --json` into a fresh folder.
fn process_until_normals(capture: &Path, calib: &std::ffi::OsStr) -> serde_json::Value {
    let out = tempfile::tempdir().unwrap();
    run_json(
        mlsss()
            .arg("process")
            .arg(capture)
            .arg("--calib")
            .arg(calib)
            .args(["--until", "normals", "--json", "--out"])
            .arg(out.path()),
    )
}

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
    // The kernel-aware separation (default, direct part from the specular lobe) against the
    // Nayar baseline on the same frames: measured 0.012 against 0.81 (global) and 0.10 against
    // 11.0 (direct) at this size; the targets are 0.10 and 0.30 (one body colour for
    // the image, the method before, gave 0.053 and 0.71).
    let value = |key: &str| {
        sep[key]
            .as_f64()
            .unwrap_or_else(|| panic!("{key} in {sep}"))
    };
    assert_eq!(sep["method"], "kernel");
    assert!(
        value("global_rel_rmse") < 0.5 * value("nayar_global_rel_rmse"),
        "{sep}"
    );
    assert!(
        value("direct_rel_rmse") < 0.5 * value("nayar_direct_rel_rmse"),
        "{sep}"
    );
    assert!(value("global_rel_rmse") < 0.10, "{sep}");
    assert!(value("direct_rel_rmse") < 0.30, "{sep}");
    assert!(
        sep["lobe"]["lobe_coverage"].as_f64().unwrap() > 0.9,
        "{sep}"
    );
    // One name for the demo's key and the stage's.
    assert_eq!(report["separation"], report["separate"]);
    let normals = &report["normals"];
    let mean = normals["mean_angular_error_deg"].as_f64().unwrap();
    let median = normals["median_angular_error_deg"].as_f64().unwrap();
    let p95 = normals["p95_angular_error_deg"].as_f64().unwrap();
    assert!(mean < 6.0 && median < 5.0 && p95 < 12.0, "{normals}");
    assert!(normals["coverage"].as_f64().unwrap() > 0.8, "{normals}");
    assert!(out.path().join("separate/separation.png").is_file());
    assert!(out.path().join("normals/normals.exr").is_file());
}

/// The default normals (the geometry's low frequencies with photometric detail) against
/// photometric stereo alone on the same head, both against the simulator's normals.
#[test]
fn fused_normals_beat_photometric_stereo_alone_and_cover_more_of_the_head() {
    let capture = quick_capture("head", 1);
    let out = tempfile::tempdir().unwrap();
    let normals = |source: &str| {
        let report = run_json(
            mlsss()
                .arg("process")
                .arg(&capture)
                .args(["--calib", "truth", "--until", "normals", "--json"])
                .args(["--normals-source", source, "--out"])
                .arg(out.path()),
        );
        report["normals"].clone()
    };
    let fused = normals("fused");
    assert!(out.path().join("normals/photometric_normals.exr").is_file());
    let photometric = normals("photometric");
    let value = |n: &serde_json::Value, key: &str| {
        n[key].as_f64().unwrap_or_else(|| panic!("{key} in {n}"))
    };
    assert_eq!(fused["source"], "fused");
    assert_eq!(photometric["source"], "photometric");
    // The virtual head has no detail finer than the plane fits' window: the fusion reads none
    // from the image and takes the geometry's low frequencies.
    assert!(value(&fused["fusion"], "fused") > 0.0, "{fused}");
    assert!(value(&fused["fusion"], "detail_rms_deg") < 0.5, "{fused}");
    assert!(
        value(&fused, "mean_angular_error_deg")
            < 0.8 * value(&photometric, "mean_angular_error_deg"),
        "fused {fused}\nphotometric {photometric}"
    );
    assert!(
        value(&fused, "coverage") >= value(&photometric, "coverage"),
        "fused {fused}\nphotometric {photometric}"
    );
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

/// The head scanned and processed with the booth calibrated from its own chessboard poses, as a
/// real booth would be (the calibration in the camera's frame, not the booth's): depth and normals
/// stay close to what the true calibration gives (measured at this size: depth 1.21 mm, normals
/// 3.3 degrees, against 6 poses of a narrow 230-px camera).
#[test]
fn a_head_processed_with_the_estimated_calibration_keeps_depth_and_normals_near_the_truth() {
    let capture = quick_capture("head", 1);
    let (calib, _) = estimated_calibration();
    let estimated = process_until_normals(&capture, calib.as_os_str());
    let exact = process_until_normals(&capture, "truth".as_ref());
    let number = |report: &serde_json::Value, section: &str, key: &str| {
        report[section][key]
            .as_f64()
            .unwrap_or_else(|| panic!("{section}.{key} missing in {report}"))
    };
    let depth = number(&estimated, "geometry", "depth_rmse_mm");
    let depth_exact = number(&exact, "geometry", "depth_rmse_mm");
    assert!(
        depth < 2.0 && depth < depth_exact + 1.5,
        "{depth} mm vs {depth_exact} mm"
    );
    let normals = number(&estimated, "normals", "mean_angular_error_deg");
    let normals_exact = number(&exact, "normals", "mean_angular_error_deg");
    assert!(
        normals < 6.0 && normals < normals_exact + 2.5,
        "{normals} deg vs {normals_exact} deg"
    );
    assert!(
        number(&estimated, "normals", "coverage") > 0.8,
        "{estimated}"
    );
}

#[test]
fn the_stripe_sweep_scores_both_separations_against_the_period_over_kernel_width() {
    let out = tempfile::tempdir().unwrap();
    let report = run_json(
        mlsss()
            .args([
                "bench",
                "--quick",
                "--scale-down",
                "2",
                "--stripe-sweep",
                "--minimal",
            ])
            .args([
                "--stripes",
                "3",
                "--seed",
                "5",
                "--photons",
                "4000",
                "--json",
            ])
            .arg("--cache")
            .arg(mlsss_tests::mc_cache_dir())
            .arg("--out")
            .arg(out.path()),
    );
    let rows = report["stripe_sweep"].as_array().expect("rows");
    // --minimal: the lightest and the darkest type, one stripe width.
    assert_eq!(rows.len(), 2, "{report}");
    for row in rows {
        let value = |path: &[&str]| {
            path.iter()
                .fold(row, |v, k| &v[k])
                .as_f64()
                .unwrap_or_else(|| panic!("{path:?} in {row}"))
        };
        // The booth's stripes are coarser than skin's kernel core (measured 4-15x at quick size),
        // which is why Nayar's assumption fails and the kernel-aware split pays.
        assert!(value(&["period_over_width"]) > 1.0, "{row}");
        assert!(
            value(&["kernel", "global_rel_rmse"]) < value(&["nayar", "global_rel_rmse"]),
            "{row}"
        );
        for c in 0..3 {
            let leak = row["leak_mean"][c].as_f64().unwrap();
            assert!((0.0..1.0).contains(&leak), "{row}");
        }
    }
    assert!(out.path().join("stripe_sweep.csv").is_file());
    let html = std::fs::read_to_string(out.path().join("stripe_sweep.html")).unwrap();
    assert!(html.contains("<img"), "the page embeds the plots");
}

#[test]
fn the_separation_race_scores_every_variant_and_the_lobe_beats_the_papers_chain() {
    let capture = quick_capture("head", 1);
    let out = tempfile::tempdir().unwrap();
    let report = run_json(
        mlsss()
            .arg("bench")
            .arg("--separation-race")
            .arg(&capture)
            .args(["--rounds", "1", "--json", "--out"])
            .arg(out.path()),
    );
    let rows = report["separation_race"].as_array().expect("rows");
    let names: Vec<&str> = rows
        .iter()
        .map(|r| r["variant"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["paper", "dichromatic", "lobe_with_leak", "lobe"]);
    let value = |name: &str, key: &str| {
        rows.iter()
            .find(|r| r["variant"] == name)
            .and_then(|r| r[key].as_f64())
            .unwrap_or_else(|| panic!("{key} of {name} in {report}"))
    };
    for name in names {
        assert!(value(name, "median_cpu_s") > 0.0, "{report}");
    }
    // The lobe's split against the paper's (Nayar) on the truth; reading the leak changes
    // nothing with the lobe.
    assert!(value("lobe", "direct_rel_rmse") < 0.2 * value("paper", "direct_rel_rmse"));
    assert!(value("lobe", "global_rel_rmse") < 0.2 * value("paper", "global_rel_rmse"));
    let same = |key: &str| (value("lobe", key) - value("lobe_with_leak", key)).abs() < 1e-4;
    assert!(
        same("direct_rel_rmse") && same("global_rel_rmse"),
        "{report}"
    );
    assert!(value("lobe", "normals_mean_error_deg") < value("paper", "normals_mean_error_deg"));
    assert_eq!(value("paper", "cpu_ratio_to_baseline"), 1.0);
    assert!(out.path().join("separation_race.csv").is_file());
}
