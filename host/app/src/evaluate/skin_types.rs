//! The per-skin-type table: one demo per Fitzpatrick type, reduced to the figures the skin-range
//! targets name (decode coverage and errors per projector, normals, subsurface error of MLSSS and
//! each baseline) and whether the paper's two claims hold on that type:
//! - `beats_dipole`: the multi-layered model reproduces the subsurface light better than a single
//!   isotropic diffusion profile (dipole) fitted per pixel;
//! - `beats_homogeneous`: per-pixel (inhomogeneous) parameters beat the same model with its
//!   parameters averaged over the skin.
//!
//! Both compare `relight.global_rel_rmse` of the held-out projector against the simulator's truth.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use crate::demo::DemoReport;
use crate::report::html::HtmlReport;

/// One skin type's row.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SkinTypeRow {
    /// Fitzpatrick type (`I` .. `VI`).
    pub skin: String,
    /// Epidermal melanin volume fraction of the preset.
    pub melanin: f64,
    /// Mean exposure scale of the projectors (metering; 1 = nominal).
    pub exposure_scale_mean: Option<f64>,
    /// Largest `missed_fraction` and `wrong_fraction` over the projectors, and the mean
    /// `unlit_fraction`.
    pub decode_missed_max: Option<f64>,
    pub decode_wrong_max: Option<f64>,
    pub decode_unlit_mean: Option<f64>,
    pub normals_mean_angular_error_deg: Option<f64>,
    /// Mean over the projectors of the profiles stage's `direct_weight_mean`: how much of the
    /// separated direct light `--direct auto` removed from the slit frames (0 none, 1 all).
    #[serde(default)]
    pub direct_weight_mean: Option<f64>,
    /// `relight.global_rel_rmse` per renderer (`mlsss`, `homogeneous`, `dipole`).
    pub global_rel_rmse: BTreeMap<String, f64>,
    pub beats_homogeneous: Option<bool>,
    pub beats_dipole: Option<bool>,
}

/// The table and the comparisons across types.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SkinTypeTable {
    pub rows: Vec<SkinTypeRow>,
    /// MLSSS subsurface error of the darkest type over that of the lightest (target <= 1.5).
    pub darkest_over_lightest_mlsss: Option<f64>,
    /// Largest minus smallest mean normal error over the types, degrees (target <= 1).
    pub normals_spread_deg: Option<f64>,
}

/// The row of one demo report (`skin`: its type label, `melanin`: its melanin fraction).
pub fn row_from_demo(skin: &str, melanin: f64, report: &DemoReport) -> SkinTypeRow {
    let projectors = report
        .decode
        .as_ref()
        .map(|d| d.projectors.as_slice())
        .unwrap_or(&[]);
    let truth = |f: fn(&crate::geometry::gray_code::TruthComparison) -> f64| {
        projectors
            .iter()
            .filter_map(|p| p.truth.as_ref().map(f))
            .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))))
    };
    let unlit: Vec<f64> = projectors
        .iter()
        .filter_map(|p| p.counts.map(|c| c.unlit_fraction))
        .collect();
    let global_rel_rmse = report
        .relight
        .as_ref()
        .and_then(|r| r.global_rel_rmse.clone())
        .unwrap_or_default();
    let mlsss = global_rel_rmse.get("mlsss").copied();
    let beats = |baseline: &str| Some(mlsss? < *global_rel_rmse.get(baseline)?);
    let exposure: Vec<f64> = report
        .demo
        .as_ref()
        .map(|d| d.exposure.iter().map(|e| e.scale).collect())
        .unwrap_or_default();
    let direct_weights: Vec<f64> = report
        .profiles
        .as_ref()
        .map(|p| {
            p.projectors
                .iter()
                .filter_map(|q| q.direct_weight_mean)
                .collect()
        })
        .unwrap_or_default();
    SkinTypeRow {
        skin: skin.to_owned(),
        direct_weight_mean: mean(&direct_weights),
        melanin,
        exposure_scale_mean: mean(&exposure).or(report.demo.as_ref().map(|_| 1.0)),
        decode_missed_max: truth(|t| t.missed_fraction),
        decode_wrong_max: truth(|t| t.wrong_fraction),
        decode_unlit_mean: mean(&unlit),
        normals_mean_angular_error_deg: report
            .normals
            .as_ref()
            .and_then(|n| n.truth.as_ref().map(|t| t.mean_angular_error_deg)),
        beats_homogeneous: beats("homogeneous"),
        beats_dipole: beats("dipole"),
        global_rel_rmse,
    }
}

fn mean(values: &[f64]) -> Option<f64> {
    (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
}

/// The table of `rows` (lightest type first).
pub fn table(rows: Vec<SkinTypeRow>) -> SkinTypeTable {
    let mlsss = |r: &SkinTypeRow| r.global_rel_rmse.get("mlsss").copied();
    let darkest_over_lightest_mlsss = match (rows.first(), rows.last()) {
        (Some(first), Some(last)) if rows.len() > 1 => {
            mlsss(last).zip(mlsss(first)).map(|(d, l)| d / l)
        }
        _ => None,
    };
    let normals: Vec<f64> = rows
        .iter()
        .filter_map(|r| r.normals_mean_angular_error_deg)
        .collect();
    let normals_spread_deg = (normals.len() > 1).then(|| {
        normals.iter().copied().fold(f64::MIN, f64::max)
            - normals.iter().copied().fold(f64::MAX, f64::min)
    });
    SkinTypeTable {
        rows,
        darkest_over_lightest_mlsss,
        normals_spread_deg,
    }
}

/// The table as CSV (one row per type; empty cells where a figure is missing).
pub fn to_csv(table: &SkinTypeTable) -> String {
    let mut out = String::from(
        "skin,melanin,exposure_scale_mean,decode_missed_max,decode_wrong_max,decode_unlit_mean,\
         normals_mean_angular_error_deg,global_rel_rmse_mlsss,global_rel_rmse_homogeneous,\
         global_rel_rmse_dipole,beats_homogeneous,beats_dipole,direct_weight_mean\n",
    );
    let num = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.6}"));
    let flag = |v: Option<bool>| v.map_or(String::new(), |v| v.to_string());
    for r in &table.rows {
        let g = |k: &str| num(r.global_rel_rmse.get(k).copied());
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{},{},{}",
            r.skin,
            r.melanin,
            num(r.exposure_scale_mean),
            num(r.decode_missed_max),
            num(r.decode_wrong_max),
            num(r.decode_unlit_mean),
            num(r.normals_mean_angular_error_deg),
            g("mlsss"),
            g("homogeneous"),
            g("dipole"),
            flag(r.beats_homogeneous),
            flag(r.beats_dipole),
            num(r.direct_weight_mean),
        );
    }
    out
}

/// The table as an HTML page (`mlsss bench --skin-types` writes it beside the CSV): one row
/// per type, then the targets across types.
pub fn to_html(table: &SkinTypeTable) -> HtmlReport {
    let num = |v: Option<f64>, d: usize| v.map_or("-".to_owned(), |v| format!("{v:.d$}"));
    let flag = |v: Option<bool>| v.map_or("-".to_owned(), |v| if v { "yes" } else { "no" }.into());
    let rows = table
        .rows
        .iter()
        .map(|r| {
            let g = |k: &str| num(r.global_rel_rmse.get(k).copied(), 3);
            vec![
                r.skin.clone(),
                format!("{:.1} %", r.melanin * 100.0),
                num(r.exposure_scale_mean, 2),
                num(r.decode_missed_max, 4),
                num(r.decode_wrong_max, 4),
                num(r.normals_mean_angular_error_deg, 2),
                g("mlsss"),
                g("homogeneous"),
                g("dipole"),
                flag(r.beats_homogeneous),
                flag(r.beats_dipole),
                num(r.direct_weight_mean, 2),
            ]
        })
        .collect();
    let mut html = HtmlReport::new("MLSSS across skin types");
    html.heading("Per skin type (held-out projector, simulator's truth)")
        .paragraph(
            "Decode: worst projector's lit pixels left undecoded (missed, target <= 0.03) and \
             wrong codes (target <= 0.002). Subsurface error: relative RMS error of the \
             held-out projector's subsurface light (relight.global_rel_rmse). The paper's two \
             claims: MLSSS beats the homogeneous model (per-pixel parameters matter) and the \
             dipole (layers matter). Direct weight: share of the separated direct light the \
             profiles removed (--direct auto, chosen per pixel from the data).",
        )
        .table(
            &[
                "type",
                "melanin",
                "exposure",
                "missed (max)",
                "wrong (max)",
                "normals (deg)",
                "MLSSS",
                "homogeneous",
                "dipole",
                "beats homogeneous",
                "beats dipole",
                "direct weight",
            ],
            rows,
        )
        .paragraph(&format!(
            "Darkest over lightest MLSSS error: {} (target <= 1.5). Spread of the normal error \
             over the types: {} deg (target <= 1).",
            num(table.darkest_over_lightest_mlsss, 2),
            num(table.normals_spread_deg, 2),
        ));
    html
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(skin: &str, mlsss: f64, homogeneous: f64, dipole: f64, normals: f64) -> SkinTypeRow {
        let report: DemoReport = serde_json::from_value(serde_json::json!({
            "relight": {
                "holdout_projector": 3, "patterns": [], "compared_pixels": 1,
                "psnr_db": {}, "rmse": {},
                "global_rel_rmse": {"mlsss": mlsss, "homogeneous": homogeneous, "dipole": dipole},
                "global_truth_patterns": [], "per_pattern": [], "render_seconds": 0.0,
                "margins": {"psnr_db_mlsss_minus_best_baseline": 0.0,
                    "psnr_db_mlsss_minus_homogeneous": 0.0,
                    "global_rel_rmse_homogeneous_over_mlsss": null,
                    "global_rel_rmse_dipole_over_mlsss": null}
            },
            "normals": {
                "pixels": 1, "solved": 1, "lights_used_mean": 4.0,
                "flagged": {"too_few_lights": 0, "ill_conditioned": 0, "no_signal": 0, "back_facing": 0},
                "input": "direct", "points": "geometry", "method": "robust",
                "mean_angular_error_deg": normals, "median_angular_error_deg": normals,
                "p95_angular_error_deg": normals, "compared_pixels": 1, "coverage": 1.0
            },
            "decode": {"exact_fraction": 1.0, "valid_fraction": 1.0, "wrong_fraction": 0.0,
                "projectors": [
                    {"projector": 0, "valid_fraction": 0.8, "flagged_fraction": 0.0,
                     "repaired_fraction": 0.0, "unlit_fraction": 0.2, "exact_fraction": 1.0,
                     "wrong_fraction": 0.001, "mean_abs_error_px": 0.1, "missed_fraction": 0.02},
                    {"projector": 1, "valid_fraction": 0.8, "flagged_fraction": 0.0,
                     "repaired_fraction": 0.0, "unlit_fraction": 0.1, "exact_fraction": 1.0,
                     "wrong_fraction": 0.0, "mean_abs_error_px": 0.1, "missed_fraction": 0.05}
                ]}
        }))
        .expect("a demo report");
        row_from_demo(skin, 0.1, &report)
    }

    #[test]
    fn the_html_page_has_a_row_per_type_and_the_ratio() {
        let table = table(vec![
            row("I", 0.10, 0.12, 0.30, 5.0),
            row("VI", 0.25, 0.24, 1.0, 7.0),
        ]);
        let html = to_html(&table).to_html();
        assert!(html.contains("<td>VI</td>"), "{html}");
        // 0.25 / 0.10; type VI loses to the homogeneous model.
        assert!(html.contains("2.50"), "{html}");
        assert!(html.contains("<td>no</td>"), "{html}");
    }

    #[test]
    fn rows_take_the_worst_projector_and_the_claims_compare_with_each_baseline() {
        let r = row("I", 0.10, 0.12, 0.09, 5.0);
        assert_eq!(r.decode_missed_max, Some(0.05));
        assert_eq!(r.decode_wrong_max, Some(0.001));
        assert!((r.decode_unlit_mean.unwrap() - 0.15).abs() < 1e-12);
        assert_eq!(r.beats_homogeneous, Some(true));
        assert_eq!(r.beats_dipole, Some(false));
        assert_eq!(r.normals_mean_angular_error_deg, Some(5.0));
    }

    #[test]
    fn the_table_compares_the_darkest_with_the_lightest_type() {
        let t = table(vec![
            row("I", 0.10, 0.12, 0.15, 5.0),
            row("IV", 0.12, 0.13, 0.2, 5.5),
            row("VI", 0.18, 0.2, 0.3, 6.2),
        ]);
        assert!((t.darkest_over_lightest_mlsss.unwrap() - 1.8).abs() < 1e-12);
        assert!((t.normals_spread_deg.unwrap() - 1.2).abs() < 1e-12);
        let csv = to_csv(&t);
        assert_eq!(csv.lines().count(), 4);
        assert!(csv.lines().nth(3).unwrap().starts_with("VI,0.1,"));
        // The last column (direct weight) is empty: the report has no profiles.
        assert!(csv.lines().nth(3).unwrap().ends_with(",true,true,"));
    }
}
