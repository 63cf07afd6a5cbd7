//! The demonstration's HTML report (`OUT/report.html`): the paper's Figs. 9-11 for the scene,
//! the metrics and timings, previews of the pipeline stages and the full JSON report.

use std::path::Path;

use super::DemoReport;
use crate::evaluate::backscatter::SideErrors;
use crate::evaluate::holdout::BASELINES;
use crate::report::figures::{RelitImages, comparison_panels, scanline_plot};
use crate::report::html::{HtmlReport, HtmlReportError, Panel, png_bytes};
use crate::report::plot::PlotError;

/// Errors of the report.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DemoReportError {
    /// An image or the document could not be produced.
    #[error(transparent)]
    Html(#[from] HtmlReportError),
    /// A plot could not be drawn.
    #[error(transparent)]
    Plot(#[from] PlotError),
}

/// The held-out relighting images the figures show.
#[derive(Debug, Clone)]
pub struct RelightFigures {
    /// Per pattern (white first when present).
    pub images: Vec<RelitImages>,
    /// Compared pixels.
    pub mask: Vec<bool>,
}

/// The back-scatter figure and its numbers (simulated captures only).
fn backscatter_section(html: &mut HtmlReport, report: &DemoReport, processed: &Path) {
    let Some(b) = report.relight.as_ref().and_then(|r| r.backscatter.as_ref()) else {
        return;
    };
    html.heading("Back-scatter: light emerging on the side the light came from");
    let ratio = |name: &str| fmt(b.asymmetry_toward_over_away.get(name).copied(), 3);
    let side = |side: &SideErrors, name: &str| fmt(side.rel_rmse.get(name).copied().flatten(), 3);
    let (toward, away) = (&b.toward_light, &b.away_from_light);
    html.paragraph(&format!(
        "Held-out slits (both axes, {} pixels): light emerging toward the light per unit \
         emerging away from it: truth {}, MLSSS {}, homogeneous {}, dipole {}. Relative error \
         of the subsurface light on the side toward the light: MLSSS {}, homogeneous {}, dipole \
         {}; on the side away from it: {}, {}, {}.",
        fmt(Some(b.pixels as f64), 0),
        ratio("truth"),
        ratio("mlsss"),
        ratio("homogeneous"),
        ratio("dipole"),
        side(toward, "mlsss"),
        side(toward, "homogeneous"),
        side(toward, "dipole"),
        side(away, "mlsss"),
        side(away, "homogeneous"),
        side(away, "dipole"),
    ));
    let panels: Vec<Panel> = Panel::from_file(
        "mean profile across the held-out projector's slits",
        &processed.join(crate::demo::BACKSCATTER_PLOT),
    )
    .into_iter()
    .collect();
    html.figure(
        "Mean subsurface light against the signed distance from the slit centre.",
        panels,
    );
}

/// `v` with `decimals` decimals, `-` when absent or not finite.
fn fmt(v: Option<f64>, decimals: usize) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.decimals$}"),
        _ => "-".into(),
    }
}

fn metric_rows(report: &DemoReport) -> Vec<Vec<String>> {
    let relight = report.relight.as_ref();
    BASELINES
        .iter()
        .map(|(_, r)| {
            vec![
                (*r).to_owned(),
                fmt(relight.and_then(|x| x.psnr(r)), 2),
                fmt(relight.and_then(|x| x.rmse_of(r)), 5),
                fmt(relight.and_then(|x| x.global_rel_rmse_of(r)), 4),
            ]
        })
        .collect()
}

fn pipeline_rows(report: &DemoReport) -> Vec<Vec<String>> {
    let errors = report.calibration.as_ref().and_then(|c| c.errors.as_ref());
    let estimate = report
        .calibration
        .as_ref()
        .and_then(|c| c.estimate.as_ref());
    [
        (
            "decode exact fraction",
            report.decode.as_ref().and_then(|d| d.exact_fraction),
            4,
        ),
        ("depth RMSE (mm)", report.depth_rmse_mm, 3),
        (
            "normals mean angular error (deg)",
            report
                .normals
                .as_ref()
                .and_then(|n| n.truth.map(|t| t.mean_angular_error_deg)),
            2,
        ),
        (
            "separation global relative RMSE",
            report.separation.and_then(|s| s.global_rel_rmse),
            3,
        ),
        (
            "calibration: max focal error (%)",
            errors.map(|e| e.max_focal_rel_pct),
            3,
        ),
        (
            "calibration: max principal point error (px)",
            errors.map(|e| e.max_principal_point_px),
            2,
        ),
        (
            "calibration: max projector centre error (mm)",
            errors.map(|e| e.max_projector_centre_mm),
            2,
        ),
        (
            "calibration: stereo RMS (px)",
            estimate.map(|e| e.stereo_rms_px),
            3,
        ),
        ("peak memory (MB)", report.peak_memory_mb, 0),
    ]
    .iter()
    .map(|(name, value, d)| vec![(*name).to_owned(), fmt(*value, *d)])
    .collect()
}

fn timing_rows(report: &DemoReport) -> Vec<Vec<String>> {
    report
        .timing_s
        .iter()
        .map(|(k, v)| vec![k.clone(), fmt(Some(*v), 2)])
        .collect()
}

/// Writes the report to `path`. `processed` is the pipeline's output folder (stage previews are
/// embedded when present).
pub fn write_report(
    path: &Path,
    report: &DemoReport,
    relight: Option<&RelightFigures>,
    processed: &Path,
) -> Result<(), DemoReportError> {
    let mut html = HtmlReport::new("MLSSS demo: held-out relighting of a simulated capture");
    html.paragraph(&intro(report));
    relighting_section(&mut html, report);
    if let Some(fig) = relight {
        figures_section(&mut html, report, fig, processed)?;
    } else {
        html.paragraph("No relighting in this run (no fitted model).");
    }
    html.heading("Pipeline against the truth");
    html.table(&["quantity", "value"], pipeline_rows(report));
    previews_section(&mut html, processed);
    html.heading("Timings (s)");
    html.table(&["step", "seconds"], timing_rows(report));
    html.heading("Full report (JSON)");
    html.preformatted(&serde_json::to_string_pretty(report).unwrap_or_default());
    html.save(path)?;
    Ok(())
}

/// The opening paragraph: the scene of a demo run (or just the held-out projector) and where
/// the calibration came from.
fn intro(report: &DemoReport) -> String {
    let source = report
        .calibration
        .as_ref()
        .map_or("?", |c| c.source.as_str());
    match &report.demo {
        Some(d) => format!(
            "Booth {}, camera [{},{}], subject {}, skin {}, seed {}; projector {} held out of the \
             fit and relit from the model fitted on the other projectors; calibration: {source}.",
            d.booth, d.camera[0], d.camera[1], d.subject, d.skin, d.seed, d.holdout_projector,
        ),
        None => format!(
            "Held-out relighting of projector {}; calibration: {source}.",
            report
                .relight
                .as_ref()
                .map_or_else(|| "?".to_owned(), |r| r.holdout_projector.to_string()),
        ),
    }
}

/// The held-out relighting metrics per renderer, and MLSSS's margins over the baselines.
fn relighting_section(html: &mut HtmlReport, report: &DemoReport) {
    html.heading("Held-out relighting");
    html.paragraph(
        "PSNR and RMSE: total render (direct + subsurface) against the recorded frames of the \
         held-out projector minus the other projectors' stray black light, pooled over the \
         evaluated patterns (peak 1.0 = camera saturation). Global relative RMSE: the rendered \
         subsurface part alone against the simulator's true global image.",
    );
    html.table(
        &["renderer", "PSNR (dB)", "RMSE", "global relative RMSE"],
        metric_rows(report),
    );
    if let Some(relight) = &report.relight {
        let margins = &relight.margins;
        html.paragraph(&format!(
            "Margins: MLSSS minus the best baseline {} dB; MLSSS minus homogeneous {} dB; global \
             error ratio homogeneous / MLSSS {}, dipole / MLSSS {}.",
            fmt(Some(margins.psnr_db_mlsss_minus_best_baseline), 2),
            fmt(Some(margins.psnr_db_mlsss_minus_homogeneous), 2),
            fmt(margins.global_rel_rmse_homogeneous_over_mlsss, 3),
            fmt(margins.global_rel_rmse_dipole_over_mlsss, 3),
        ));
    }
}

/// The paper's Figs. 9-11 from the held-out relighting images, then the back-scatter figure.
fn figures_section(
    html: &mut HtmlReport,
    report: &DemoReport,
    fig: &RelightFigures,
    processed: &Path,
) -> Result<(), DemoReportError> {
    if let Some(code) = fig.images.iter().find(|i| i.pattern != "white") {
        html.heading("Fig. 9: recorded vs rendered under a code pattern");
        html.figure(
            "The held-out projector's Gray-code pattern: recorded, then each renderer (same \
             exposure).",
            comparison_panels(code, &fig.mask)?,
        );
    }
    html.heading("Fig. 10: forehead scanline");
    html.figure(
        "R channel along a forehead row (a quarter down the subject).",
        fig10_panels(fig, processed)?,
    );
    if let Some(white) = fig.images.iter().find(|i| i.pattern == "white") {
        html.heading("Fig. 11: white light, inhomogeneous vs homogeneous vs recorded");
        html.figure(
            "The held-out projector's white frame: recorded, then each renderer.",
            comparison_panels(white, &fig.mask)?,
        );
    }
    backscatter_section(html, report, processed);
    Ok(())
}

/// Fig. 10's panels: the scanline of each relit pattern, then the fit and profiles stages' own
/// scanline plots when present.
fn fig10_panels(fig: &RelightFigures, processed: &Path) -> Result<Vec<Panel>, DemoReportError> {
    let mut panels = Vec::new();
    for images in &fig.images {
        if let Some(plot) = scanline_plot(images, &fig.mask, 0)? {
            let label = format!("R channel, held-out projector, {}", images.pattern);
            panels.push(Panel::png(&label, png_bytes(&plot.render()?, &label)?));
        }
    }
    for (file, label) in [
        (
            "fit/fig10.svg",
            "fit stage: R along the scanline, measured vs synthesised",
        ),
        (
            "fit/pixel_profiles.svg",
            "fit stage: profiles of three scanline pixels",
        ),
        (
            "profiles/scanline.svg",
            "profiles stage: measured global light on the scanline",
        ),
    ] {
        panels.extend(Panel::from_file(label, &processed.join(file)));
    }
    Ok(panels)
}

/// The stages' preview images found in `processed` (none: no figure).
fn previews_section(html: &mut HtmlReport, processed: &Path) {
    let previews: Vec<Panel> = [
        (
            "separate/separation.png",
            "direct / global separation (rows: projectors)",
        ),
        ("normals/normals.png", "normals"),
        ("geometry/shaded.png", "geometry"),
    ]
    .iter()
    .filter_map(|(f, l)| Panel::from_file(l, &processed.join(f)))
    .collect();
    if !previews.is_empty() {
        html.figure("Stage previews.", previews);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evaluate::holdout::{Margins, RelightReport};

    #[test]
    fn the_report_holds_metrics_figures_and_previews() {
        let dir = tempfile::tempdir().unwrap();
        let processed = dir.path().join("processed");
        std::fs::create_dir_all(processed.join("normals")).unwrap();
        image::RgbImage::new(4, 4)
            .save(processed.join("normals/normals.png"))
            .unwrap();
        let report = DemoReport {
            demo: Some(crate::demo::DemoInfo {
                booth: "quick".into(),
                camera: [4, 4],
                subject: "head".into(),
                skin: "light".into(),
                seed: 1,
                holdout_projector: 3,
                calibration: crate::demo::CalibrationMode::Truth,
                monte_carlo: crate::demo::MonteCarloCounts {
                    cached: 0,
                    computed: 0,
                },
                out: dir.path().to_owned(),
                exposure: Vec::new(),
            }),
            relight: Some(RelightReport {
                psnr_db: [("mlsss".into(), 31.25), ("homogeneous".into(), 29.5)].into(),
                rmse: [("mlsss".into(), 0.0274)].into(),
                margins: Margins {
                    psnr_db_mlsss_minus_best_baseline: 1.75,
                    ..Margins::default()
                },
                ..RelightReport::default()
            }),
            depth_rmse_mm: Some(0.25),
            timing_s: [("simulate".into(), 3.5), ("total".into(), 9.0)].into(),
            ..DemoReport::default()
        };
        let mask = vec![true; 16];
        let img = |v: f32| vec![[v, v * 0.5, v * 0.25]; 16];
        let images = |pattern: &str| RelitImages {
            pattern: pattern.into(),
            width: 4,
            height: 4,
            reference: img(0.5),
            renders: vec![
                ("mlsss".into(), img(0.45)),
                ("homogeneous".into(), img(0.3)),
            ],
        };
        let fig = RelightFigures {
            images: vec![images("white"), images("gray-x-3")],
            mask,
        };
        let path = dir.path().join("report.html");
        write_report(&path, &report, Some(&fig), &processed).unwrap();
        let html = std::fs::read_to_string(&path).unwrap();
        assert!(html.contains("<td>mlsss</td><td>31.25</td><td>0.02740</td><td>-</td>"));
        assert!(html.contains("Fig. 9") && html.contains("Fig. 10") && html.contains("Fig. 11"));
        assert!(html.contains("recorded (gray-x-3)") && html.contains("homogeneous (white)"));
        assert!(html.contains("MLSSS minus the best baseline 1.75 dB"));
        assert!(html.contains("<td>depth RMSE (mm)</td><td>0.250</td>"));
        assert!(html.contains("alt=\"normals\""));
        // 3 + 3 comparison panels, 2 scanline plots, 1 preview.
        assert_eq!(html.matches("data:image/png;base64,").count(), 9);
        // Without relighting the report still renders and says so.
        write_report(&path, &report, None, &processed).unwrap();
        let html = std::fs::read_to_string(&path).unwrap();
        assert!(html.contains("No relighting in this run"));
    }
}
