//! Monte Carlo transport (`mlsss::mc`) against exact values: adding-doubling, the published MCML
//! anchors, and the oblique-incidence shift of diffusion theory.
//!
//! Pass criterion for every value: within 3 standard errors AND within 1% relative of the exact
//! value. Photon counts are chosen so one standard error is about 0.3% relative or less (then the 1%
//! bound is 3 standard errors away too), within the test-time budget.

use mlsss::mc::{self, GridSpec, Layer, McConfig, McResult, Medium};

/// One adding-doubling reference case (see `scripts/iad_reference.py`).
struct Case {
    name: &'static str,
    albedo: f64,
    tau: f64,
    g: f64,
    n: f64,
    /// Index of a non-absorbing glass slide above / below; equal to `n` means no slide.
    n_slide_above: f64,
    n_slide_below: f64,
    specular: f64,
    diffuse_reflectance: f64,
    total_transmittance: f64,
}

// Produced by `python3 scripts/iad_reference.py` with iadpython 0.5.3 (pip install iadpython==0.5.3);
// the script documents how UR1/UT1 map to these fields and how the quadrature order was chosen.
// (name, a, tau, g, n, n_slide_above, n_slide_below, specular, diffuse R, total T)
#[rustfmt::skip]
const ADDING_DOUBLING: &[Case] = &[
    Case { name: "mcml_slab_matched", albedo: 0.9, tau: 2.0, g: 0.75, n: 1.0, n_slide_above: 1.0, n_slide_below: 1.0, specular: 0.000000, diffuse_reflectance: 0.097400, total_transmittance: 0.660957 }, // quad_pts 16
    Case { name: "semi_infinite_matched_iso", albedo: 0.9, tau: f64::INFINITY, g: 0.0, n: 1.0, n_slide_above: 1.0, n_slide_below: 1.0, specular: 0.000000, diffuse_reflectance: 0.414947, total_transmittance: 0.000000 }, // quad_pts 16
    Case { name: "thin_low_albedo_water", albedo: 0.5, tau: 0.5, g: 0.0, n: 1.33, n_slide_above: 1.33, n_slide_below: 1.33, specular: 0.020059, diffuse_reflectance: 0.046089, total_transmittance: 0.620307 }, // quad_pts 20
    Case { name: "high_albedo_mismatched", albedo: 0.99, tau: 1.0, g: 0.5, n: 1.4, n_slide_above: 1.4, n_slide_below: 1.4, specular: 0.027778, diffuse_reflectance: 0.211232, total_transmittance: 0.727631 }, // quad_pts 24
    Case { name: "backward_g_mismatched", albedo: 0.8, tau: 2.0, g: -0.3, n: 1.2, n_slide_above: 1.2, n_slide_below: 1.2, specular: 0.008264, diffuse_reflectance: 0.256359, total_transmittance: 0.226256 }, // quad_pts 28
    Case { name: "glass_slides_forward", albedo: 0.95, tau: 4.0, g: 0.9, n: 1.4, n_slide_above: 1.5, n_slide_below: 1.5, specular: 0.040000, diffuse_reflectance: 0.081459, total_transmittance: 0.537823 }, // quad_pts 40
    Case { name: "slide_above_only_iso", albedo: 0.95, tau: 3.0, g: 0.0, n: 1.4, n_slide_above: 1.5, n_slide_below: 1.4, specular: 0.040000, diffuse_reflectance: 0.333625, total_transmittance: 0.252332 }, // quad_pts 28
    Case { name: "semi_infinite_skinlike", albedo: 0.98, tau: f64::INFINITY, g: 0.8, n: 1.4, n_slide_above: 1.4, n_slide_below: 1.4, specular: 0.027778, diffuse_reflectance: 0.250023, total_transmittance: 0.000000 }, // quad_pts 32
    Case { name: "thick_fat_layer", albedo: 0.998003992015968, tau: 88.677, g: 0.8, n: 1.44, n_slide_above: 1.44, n_slide_below: 1.44, specular: 0.032518, diffuse_reflectance: 0.586700, total_transmittance: 0.026310 }, // quad_pts 32
];

/// Photons per case, same order as `ADDING_DOUBLING` (costs differ by two orders of magnitude).
/// The thick fat layer's million (~1,300 events each) put its diffuse reflectance's standard error
/// at 0.06 %: MCML's own generator is 0.17 % low there (`benches/mcml_rng_bias.py`), ours is not.
const PHOTONS: &[u64] = &[
    1_000_000, 200_000, 600_000, 200_000, 200_000, 600_000, 200_000, 100_000, 1_000_000,
];

/// A glass slide: a clear layer (no absorption, no scattering); its thickness does not matter.
fn slide(n: f64) -> Layer {
    Layer {
        thickness_mm: 1.0,
        mu_a: 0.0,
        mu_s: 0.0,
        g: 0.0,
        n,
    }
}

/// The sample between its slides, in air.
fn medium(case: &Case) -> Medium {
    let mut layers = Vec::new();
    if case.n_slide_above != case.n {
        layers.push(slide(case.n_slide_above));
    }
    layers.push(Layer::from_albedo(case.albedo, case.tau, case.g, case.n));
    if case.n_slide_below != case.n && case.tau.is_finite() {
        layers.push(slide(case.n_slide_below));
    }
    Medium {
        layers,
        n_above: 1.0,
        n_below: 1.0,
    }
}

/// One compared value; `None` if it passes, else a description of the failure.
fn compare(label: &str, mc: f64, se: f64, exact: f64, table: &mut String) -> Option<String> {
    let rel = if exact != 0.0 {
        (mc - exact) / exact
    } else {
        mc - exact
    };
    let within_se = (mc - exact).abs() <= 3.0 * se;
    let within_rel = rel.abs() <= 0.01;
    let ok = within_se && within_rel;
    table.push_str(&format!(
        "| {label} | {mc:.5} ± {se:.5} | {exact:.5} | {:+.3}% | {} |\n",
        100.0 * rel,
        if ok { "ok" } else { "FAIL" }
    ));
    (!ok).then(|| {
        format!(
            "{label}: {mc} ± {se} vs exact {exact} ({:+.3}%)",
            100.0 * rel
        )
    })
}

fn check_case(case: &Case, result: &McResult, table: &mut String) -> Vec<String> {
    let mut failures = Vec::new();
    if (result.specular - case.specular).abs() > 1e-6 {
        failures.push(format!(
            "{}: specular {} vs {}",
            case.name, result.specular, case.specular
        ));
    }
    let label = format!("{} R_d", case.name);
    failures.extend(compare(
        &label,
        result.diffuse_reflectance,
        result.diffuse_reflectance_se,
        case.diffuse_reflectance,
        table,
    ));
    if case.tau.is_finite() {
        let label = format!("{} T", case.name);
        failures.extend(compare(
            &label,
            result.total_transmittance,
            result.total_transmittance_se,
            case.total_transmittance,
            table,
        ));
    } else if result.total_transmittance != 0.0 {
        failures.push(format!("{}: semi-infinite medium transmits", case.name));
    }
    failures
}

#[test]
fn slabs_match_adding_doubling() {
    assert_eq!(ADDING_DOUBLING.len(), PHOTONS.len());
    let mut table = String::from("| case | MC ± SE | exact | rel | |\n|---|---|---|---|---|\n");
    let mut failures = Vec::new();
    for (i, (case, &photons)) in ADDING_DOUBLING.iter().zip(PHOTONS).enumerate() {
        let cfg = McConfig::new(photons, 1000 + i as u64);
        let result = mc::run(&medium(case), &cfg).unwrap();
        failures.extend(check_case(case, &result, &mut table));
    }
    eprintln!("{table}");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// DESIGN section 10: MCML's slab (n = 1, mu_a = 10/cm, mu_s = 90/cm, g = 0.75, d = 0.02 cm;
/// van de Hulst's R_d 0.09739, T 0.66096) and the semi-infinite matched medium, albedo 0.9, g = 0
/// (R_d 0.41495), in physical units rather than optical ones.
#[test]
fn published_mcml_anchors() {
    let mut table = String::new();
    let slab = Layer {
        thickness_mm: 0.2,
        mu_a: 1.0,
        mu_s: 9.0,
        g: 0.75,
        n: 1.0,
    };
    let r = mc::run(&Medium::slab(slab, 1.0, 1.0), &McConfig::new(1_000_000, 7)).unwrap();
    let mut failures: Vec<String> = Vec::new();
    failures.extend(compare(
        "mcml slab R_d",
        r.diffuse_reflectance,
        r.diffuse_reflectance_se,
        0.09739,
        &mut table,
    ));
    failures.extend(compare(
        "mcml slab T",
        r.total_transmittance,
        r.total_transmittance_se,
        0.66096,
        &mut table,
    ));
    let semi = Layer {
        thickness_mm: f64::INFINITY,
        mu_a: 0.1,
        mu_s: 0.9,
        g: 0.0,
        n: 1.0,
    };
    let r = mc::run(&Medium::slab(semi, 1.0, 1.0), &McConfig::new(200_000, 8)).unwrap();
    failures.extend(compare(
        "semi-infinite a=0.9 g=0 R_d",
        r.diffuse_reflectance,
        r.diffuse_reflectance_se,
        0.41495,
        &mut table,
    ));
    // Energy is conserved in expectation: R_d + T + absorbed + specular = 1.
    let sum = r.specular + r.diffuse_reflectance + r.total_transmittance + r.absorbed[0];
    assert!(
        (sum - 1.0).abs() < 5.0 * r.diffuse_reflectance_se,
        "sum {sum}"
    );
    eprintln!("{table}");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Wang & Jacques 1995: under oblique incidence the diffuse reflectance is centred at
/// dx = sin(theta_t) / (mu_a + mu_s') from the entry point, forward (away from the light).
#[test]
fn oblique_incidence_shifts_the_exit_centroid_forward() {
    let g = 0.8;
    let mu_s_reduced = 1.0;
    let layer = Layer {
        thickness_mm: f64::INFINITY,
        mu_a: 0.1,
        mu_s: mu_s_reduced / (1.0 - g),
        g,
        n: 1.4,
    };
    let medium = Medium::slab(layer, 1.0, 1.0);
    for (angle, seed) in [(45.0f64, 11), (60.0, 12)] {
        let cfg = McConfig {
            incidence_deg: angle,
            grid: Some(GridSpec {
                cell_mm: 0.2,
                cells: 201,
            }),
            ..McConfig::new(20_000, seed)
        };
        let r = mc::run(&medium, &cfg).unwrap();
        let sin_t = angle.to_radians().sin() / 1.4;
        let predicted = sin_t / (layer.mu_a + mu_s_reduced);
        let [x, y] = r.exit_centroid_mm;
        let grid = r.response.as_ref().unwrap();
        let [gx, _] = grid.centroid_mm();
        eprintln!(
            "oblique {angle} deg: centroid x {x:.4} mm (grid {gx:.4}), y {y:.4}, predicted {predicted:.4}, grid holds {:.4} of R_d {:.4}",
            grid.total(),
            r.diffuse_reflectance
        );
        assert!(
            ((x - predicted) / predicted).abs() < 0.2,
            "{angle} deg: centroid {x} vs {predicted}"
        );
        // The grid tabulates the same response: its centroid agrees when little falls outside.
        assert!(grid.outside < 0.01 * r.diffuse_reflectance);
        assert!((gx - x).abs() < 0.05 * predicted, "grid {gx} vs {x}");
        // No sideways shift (mirror symmetry about the plane of incidence).
        assert!(y.abs() < 0.1 * predicted, "y {y}");
    }
}
