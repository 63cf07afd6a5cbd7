//! `mlsss mc`: JSON contract and error messages of the Monte Carlo subcommands.

use mlsss_tests::mlsss;

fn run_json(args: &[&str]) -> serde_json::Value {
    let out = mlsss().args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert_eq!(
        stdout.trim().lines().count(),
        1,
        "one JSON object: {stdout}"
    );
    serde_json::from_str(&stdout).unwrap()
}

fn num(v: &serde_json::Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("missing key {key} in {v}"))
}

#[test]
fn slab_json_has_the_issue_keys_and_the_mcml_value() {
    let v = run_json(&[
        "mc",
        "slab",
        "--albedo",
        "0.9",
        "--tau",
        "2",
        "--g",
        "0.75",
        "--photons",
        "50000",
        "--seed",
        "3",
        "--json",
    ]);
    for key in [
        "specular",
        "diffuse_reflectance",
        "diffuse_reflectance_se",
        "total_transmittance",
        "total_transmittance_se",
        "photons",
        "photons_per_second",
        "interactions_per_second",
        "interactions_per_photon",
    ] {
        assert!(v[key].is_number(), "{key} in {v}");
    }
    assert_eq!(v["photons"], 50000);
    // Interactions per second is the photon rate times the interactions per photon.
    let ratio = num(&v, "interactions_per_second")
        / (num(&v, "photons_per_second") * num(&v, "interactions_per_photon"));
    assert!((ratio - 1.0).abs() < 1e-9, "{v}");
    assert!(v["simd"].is_string(), "{v}");
    // van de Hulst / MCML: R_d 0.09739, T 0.66096.
    let rd = num(&v, "diffuse_reflectance");
    let t = num(&v, "total_transmittance");
    assert!(
        (rd - 0.09739).abs() < 4.0 * num(&v, "diffuse_reflectance_se"),
        "{v}"
    );
    assert!(
        (t - 0.66096).abs() < 4.0 * num(&v, "total_transmittance_se"),
        "{v}"
    );
    assert_eq!(v["absorbed"].as_array().unwrap().len(), 1);
}

#[test]
fn semi_infinite_slab_from_tau_inf_transmits_nothing() {
    let v = run_json(&[
        "mc",
        "slab",
        "--albedo",
        "0.5",
        "--tau",
        "inf",
        "--n",
        "1.4",
        "--photons",
        "2000",
        "--json",
    ]);
    assert_eq!(num(&v, "total_transmittance"), 0.0);
    // Normal incidence air -> 1.4.
    assert!((num(&v, "specular") - (0.4f64 / 2.4).powi(2)).abs() < 1e-12);
}

#[test]
fn layers_file_gives_one_absorbed_value_per_layer() {
    let file = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../host/monte-carlo/data/skin-layers.toml"
    );
    let v = run_json(&[
        "mc",
        "layers",
        "--file",
        file,
        "--angle",
        "30",
        "--photons",
        "4000",
        "--json",
    ]);
    let absorbed: Vec<f64> = v["absorbed"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a.as_f64().unwrap())
        .collect();
    assert_eq!(absorbed.len(), 2);
    let total = num(&v, "specular") + num(&v, "diffuse_reflectance") + absorbed.iter().sum::<f64>();
    assert!((total - 1.0).abs() < 0.02, "energy {total} in {v}");
}

#[test]
fn bad_layers_file_names_file_line_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad-layers.toml");
    std::fs::write(
        &path,
        "n_above = 1.0\n[[layer]]\nthickness_mm = 1.0\nmu_a = 0.1\nmu_s = 10.0\ng = 0.9\nindex = 1.4\n",
    )
    .unwrap();
    let out = mlsss()
        .args(["mc", "layers", "--json", "--file"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(out.stdout.is_empty());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad-layers.toml:7"), "{err}");
    assert!(err.contains("index"), "{err}");
}

#[test]
fn out_of_range_angle_is_refused() {
    let out = mlsss()
        .args([
            "mc", "slab", "--albedo", "0.9", "--tau", "1", "--angle", "95", "--json",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("incidence_deg"));
}
