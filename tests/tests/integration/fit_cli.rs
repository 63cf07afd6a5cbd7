//! `mlsss process --until fit` and `mlsss render` end to end on a tiny simulated head capture:
//! the slit frames' global part against the simulator's, the fitted model's held-out renders
//! against the truth and the baselines, and the model file through `mlsss render`.

use std::path::Path;

use mlsss_tests::{fitted_head as fitted, mlsss};

fn number(v: &serde_json::Value, path: &str) -> f64 {
    path.split('.')
        .fold(v, |v, key| &v[key])
        .as_f64()
        .unwrap_or_else(|| panic!("{path} missing in {v}"))
}

#[test]
fn slit_global_matches_the_simulator_truth() {
    let (_, report) = fitted();
    let p = &report["profiles"];
    let err = number(p, "slit_global_rel_rmse");
    eprintln!("slit global relative RMSE {err:.3} ({p})");
    assert!(err < 0.25, "global part of the slit frames: {err}");
    // `--compare-slit-variants` decodes every slit frame again and extracts it by each rule;
    // the fixture's rule (`--direct none`) must reproduce the stage's own extraction.
    let again = number(p, "slit_global_rel_rmse_direct_none");
    assert!(
        (again - err).abs() <= 1e-9 * err,
        "re-extracted {again} against {err}"
    );
    for rule in [
        "hard_mask",
        "direct_separation",
        "direct_colourless",
        "direct_auto",
    ] {
        let key = format!("slit_global_rel_rmse_{rule}");
        assert!(number(p, &key).is_finite(), "{key}");
    }
    for k in 0..4 {
        assert_eq!(p["projectors"][k]["slit_frames"], 20);
        assert!(p["projectors"][k]["pixels_with_profiles"].as_u64().unwrap() > 1000);
    }
    // Where the stage's time went: every phase, within the stage's own wall clock.
    let phases: Vec<f64> = ["load", "report", "truth", "write"]
        .iter()
        .map(|phase| number(p, &format!("phase_s.{phase}")))
        .collect();
    assert!(phases.iter().all(|s| *s >= 0.0), "{phases:?}");
    let stage = number(report, "timing_s.profiles");
    assert!(
        phases.iter().sum::<f64>() <= stage,
        "phases {phases:?} against the stage's {stage} s"
    );
}

#[test]
fn the_fitted_model_predicts_the_held_out_projector_better_than_the_homogeneous_one() {
    let (out, report) = fitted();
    let f = &report["fit"];
    eprintln!("fit report: {f}");
    assert_eq!(f["training_projectors"], serde_json::json!([0, 1, 2]));
    assert_eq!(f["holdout"], 3);
    let d = number(f, "depth_spacing_mm");
    // The quick booth cannot resolve depth (projector pixels of ~2.3 mm on the face): D may be 0.
    assert!((0.0..1.0).contains(&d), "layer spacing {d} mm");
    let layers = number(f, "components_mean");
    assert!((1.0..=4.0).contains(&layers), "{layers}");
    assert!(f["pixels_fitted"].as_u64().unwrap() > 1000);
    // With the spatial prior (default) the per-pixel model beats the homogeneous one under
    // white light too (0.082 vs 0.085 here; without the prior 0.101 vs 0.090). The homogeneous
    // baseline averages the regularised layers per layer identity (depth and width), i.e. the
    // same kernel with the mean amplitude: on the slits the two are within a few per cent.
    let white = &f["heldout_global_rel_rmse"]["white"];
    let (ours_white, homog_white) = (number(white, "mlsss"), number(white, "homogeneous"));
    assert!(
        ours_white < 0.2,
        "white: held-out global relative RMSE {ours_white}"
    );
    assert!(
        ours_white < homog_white,
        "white: ours {ours_white} vs homogeneous {homog_white}"
    );
    let prior = &f["spatial_prior"]["channels"];
    for c in 0..3 {
        let keep = number(&prior[c], "mean_keep_fraction");
        assert!(
            (0.0..=1.0).contains(&keep),
            "channel {c}: keep fraction {keep}"
        );
        assert!(prior[c]["cv_log_likelihood"]["global"].is_f64(), "{prior}");
    }
    // The paper's second claim, under white light: the layers relight the face better than the
    // dipole (0.087 vs 0.093 here).
    let dipole_white = number(white, "dipole");
    assert!(
        ours_white < dipole_white,
        "white: ours {ours_white} vs dipole {dipole_white}"
    );
    // On the slits the three models are close since the profiles are weighted by their photons
    // (`--profile-weights information`): ours 0.231 -> 0.210 (x) and 0.179 -> 0.160 (y), the
    // dipole 0.256 -> 0.206 and 0.212 -> 0.158, which puts it 2 % ahead on this scene. On the
    // quick heads of `mlsss bench --skin-types` (seeds 99 and 113) ours stays ahead of both.
    for pattern in ["slit-x-o0", "slit-y-o0"] {
        let e = &f["heldout_global_rel_rmse"][pattern];
        let ours = number(e, "mlsss");
        let homog = number(e, "homogeneous");
        let dipole = number(e, "dipole");
        assert!(
            ours < 0.35,
            "{pattern}: held-out global relative RMSE {ours}"
        );
        assert!(
            ours < 1.05 * homog,
            "{pattern}: ours {ours} vs homogeneous {homog}"
        );
        assert!(
            ours < 1.05 * dipole,
            "{pattern}: ours {ours} vs dipole {dipole}"
        );
    }
    for file in [
        "model.mlsss",
        "fig10.png",
        "fig10.svg",
        "pixel_profiles.png",
        "fig10.json",
    ] {
        assert!(out.join("fit").join(file).is_file(), "{file}");
    }
}

#[test]
fn render_writes_exr_and_png_from_the_model_file() {
    let (out, _) = fitted();
    let model = out.join("fit/model.mlsss");
    let exr = out.join("renders/slit.exr");
    let run = |baseline: &str, target: &Path| {
        let output = mlsss()
            .arg("render")
            .arg(&model)
            .args(["--light", "projector:3", "--pattern", "slit-x-o2", "--json"])
            .args(["--baseline", baseline, "--out"])
            .arg(target)
            .output()
            .unwrap();
        assert!(
            output.status.success(),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        serde_json::from_slice::<serde_json::Value>(&output.stdout).unwrap()
    };
    let report = run("mlsss", &exr);
    assert_eq!(report["pattern"], "slit-x-o2");
    assert!(exr.is_file() && exr.with_extension("png").is_file());
    let direct = out.join("renders/direct.exr");
    run("direct", &direct);
    // The subsurface light adds to the direct part everywhere on the subject.
    let sum = |p: &Path| -> f64 {
        let img = image::open(p.with_extension("png")).unwrap().to_rgb8();
        img.pixels().map(|p| f64::from(p.0[0])).sum()
    };
    let (with, without) = (sum(&exr), sum(&direct));
    assert!(with > without, "{with} vs {without}");

    let bad = mlsss()
        .arg("render")
        .arg(&model)
        .args(["--light", "projector:9", "--out"])
        .arg(out.join("renders/bad.exr"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("projector 9"), "{err}");
}
