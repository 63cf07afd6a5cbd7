//! Separation error against the ratio of the stripe period to the subsurface kernel's width
//! (`mlsss bench --stripe-sweep`): one simulated capture per skin type and stripe width, each
//! separated by the kernel-aware method and by Nayar et al.'s, both scored against the
//! simulator's truth (`separate_stage::SeparationErrors`).
//!
//! Nayar's split assumes the global light does not follow the stripes: it holds when the stripe
//! period is small next to the kernel the light spreads over below the surface. This table shows
//! where on that axis a booth sits and how much of the error the kernel-aware split removes.
//!
//! Kernel width: the interquartile width of the kernel's *line spread* (the Monte Carlo exit
//! response of the skin's base material at normal incidence, summed along the stripes' axis):
//! half of the light entering along a line leaves within this band around it. Channels are
//! weighted by their diffuse reflectance, as the errors (sums over channels) weight them by their
//! light. Stripe period on the skin: `2 stripe` projector pixels at the projector's look-at
//! distance (mean over the projectors).

use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use crate::pipeline::separate_stage::{SeparateReport, SeparationErrors};
use crate::report::html::{HtmlReport, Panel};
use crate::report::plot::{Plot, PlotError, Style};
use mlsss_core::booth::Booth;
use mlsss_virtual_booth::subsurface_transport::ResponseGrid;

/// One (skin type, stripe width) point of the sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StripeSweepRow {
    /// Fitzpatrick type (`I` .. `VI`).
    pub skin: String,
    /// Stripe width, projector px (the period is twice this).
    pub stripe_px: u32,
    /// Stripe period on the skin, mm.
    pub period_mm: f64,
    /// Interquartile width of the kernel's line spread per channel (R, G, B), mm.
    pub kernel_width_mm: [f64; 3],
    /// The same, channels weighted by their diffuse reflectance, mm.
    pub kernel_width_weighted_mm: f64,
    /// `period_mm / kernel_width_weighted_mm`: the figure's x axis.
    pub period_over_width: f64,
    /// Mean kernel leak per channel the separation measured from the slit sweep.
    pub leak_mean: [f64; 3],
    /// Errors of the kernel-aware split (ours) and of Nayar et al.'s, against the truth.
    pub kernel: SeparationErrors,
    pub nayar: SeparationErrors,
}

/// Stripe period on the skin in mm: `2 stripe_px` projector pixels at each projector's look-at
/// distance, averaged over the projectors.
pub fn stripe_period_mm(booth: &Booth, stripe_px: u32) -> f64 {
    let pitches: Vec<f64> = booth
        .projectors
        .iter()
        .map(|p| {
            let d = nalgebra::Vector3::from(p.look_at_mm) - nalgebra::Vector3::from(p.position_mm);
            d.norm() / p.fx
        })
        .collect();
    let pitch = pitches.iter().sum::<f64>() / pitches.len().max(1) as f64;
    2.0 * stripe_px as f64 * pitch
}

/// Interquartile width (mm) of the line spread of `grid` per channel, and the width with the
/// channels weighted by their diffuse reflectance. `None` for a channel without light.
pub fn line_spread_width_mm(grid: &ResponseGrid) -> ([f64; 3], f64) {
    let n = grid.cells;
    let mut line = vec![[0.0f64; 3]; n];
    for (i, v) in grid.values.iter().enumerate() {
        for c in 0..3 {
            line[i % n][c] += v[c] as f64;
        }
    }
    let widths: [f64; 3] = std::array::from_fn(|c| {
        let column: Vec<f64> = line.iter().map(|l| l[c]).collect();
        interquartile_width(&column) * grid.cell_mm
    });
    let totals = grid.total();
    let sum: f64 = totals.iter().sum();
    let weighted = if sum > 0.0 {
        (0..3).map(|c| widths[c] * totals[c]).sum::<f64>() / sum
    } else {
        0.0
    };
    (widths, weighted)
}

/// Distance in samples between the 25th and 75th percentiles of a non-negative density sampled
/// on unit cells (linear interpolation inside a cell); 0 for an empty density.
fn interquartile_width(density: &[f64]) -> f64 {
    let total: f64 = density.iter().sum();
    if total <= 0.0 {
        return 0.0;
    }
    let quantile = |q: f64| {
        let target = q * total;
        let mut acc = 0.0;
        for (i, &d) in density.iter().enumerate() {
            if d > 0.0 && acc + d >= target {
                return i as f64 + (target - acc) / d;
            }
            acc += d;
        }
        density.len() as f64
    };
    quantile(0.75) - quantile(0.25)
}

/// The row of one capture's separation report (`None` when it has no truth comparison or no
/// kernel leak).
pub fn row(
    skin: &str,
    stripe_px: u32,
    period_mm: f64,
    (kernel_width_mm, kernel_width_weighted_mm): ([f64; 3], f64),
    report: &SeparateReport,
) -> Option<StripeSweepRow> {
    let kernel = report.truth?;
    let nayar = SeparationErrors {
        direct_rel_rmse: report.nayar_direct_rel_rmse?,
        global_rel_rmse: report.nayar_global_rel_rmse?,
        total_rel_rmse: report.nayar_total_rel_rmse?,
    };
    // The separation must have read the leak (`SeparateParams::leak_with_lobe` with the lobe).
    let leaks: Vec<[f64; 3]> = report
        .projectors
        .iter()
        .map(|p| p.leak.as_ref().map(|l| l.leak_mean))
        .collect::<Option<_>>()?;
    let projectors = leaks.len().max(1) as f64;
    let leak_mean = std::array::from_fn(|c| leaks.iter().map(|l| l[c]).sum::<f64>() / projectors);
    Some(StripeSweepRow {
        skin: skin.to_owned(),
        stripe_px,
        period_mm,
        kernel_width_mm,
        kernel_width_weighted_mm,
        period_over_width: period_mm / kernel_width_weighted_mm,
        leak_mean,
        kernel,
        nayar,
    })
}

/// The rows as CSV (header first).
pub fn to_csv(rows: &[StripeSweepRow]) -> String {
    let mut out = String::from(
        "skin,stripe_px,period_mm,kernel_width_r_mm,kernel_width_g_mm,kernel_width_b_mm,\
         kernel_width_weighted_mm,period_over_width,leak_r,leak_g,leak_b,\
         kernel_direct_rel_rmse,kernel_global_rel_rmse,nayar_direct_rel_rmse,\
         nayar_global_rel_rmse\n",
    );
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.5},{:.5},{:.5},{:.5}",
            r.skin,
            r.stripe_px,
            r.period_mm,
            r.kernel_width_mm[0],
            r.kernel_width_mm[1],
            r.kernel_width_mm[2],
            r.kernel_width_weighted_mm,
            r.period_over_width,
            r.leak_mean[0],
            r.leak_mean[1],
            r.leak_mean[2],
            r.kernel.direct_rel_rmse,
            r.kernel.global_rel_rmse,
            r.nayar.direct_rel_rmse,
            r.nayar.global_rel_rmse,
        );
    }
    out
}

/// Error against period / width, one plot per separated part (`direct` or `global`), a series per
/// method, points sorted along x.
pub fn plot(rows: &[StripeSweepRow], part: &str) -> Plot {
    let pick = |e: &SeparationErrors| match part {
        "direct" => e.direct_rel_rmse,
        _ => e.global_rel_rmse,
    };
    let series = |f: &dyn Fn(&StripeSweepRow) -> f64| {
        let mut points: Vec<(f64, f64)> =
            rows.iter().map(|r| (r.period_over_width, f(r))).collect();
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
        points
    };
    Plot::new(
        &format!("{part} light: separation error against stripe period / kernel width"),
        "stripe period / kernel line-spread width (IQR)",
        &format!("{part} rel. RMSE"),
    )
    .with_series(
        "kernel-aware (ours)",
        series(&|r| pick(&r.kernel)),
        Style::Points,
    )
    .with_series("Nayar et al.", series(&|r| pick(&r.nayar)), Style::Points)
}

/// The page `mlsss bench --stripe-sweep` writes: both plots, then the table.
pub fn to_html(rows: &[StripeSweepRow]) -> Result<HtmlReport, PlotError> {
    let panels = ["global", "direct"]
        .iter()
        .map(|part| Ok(Panel::png(part, plot(rows, part).png_bytes()?)))
        .collect::<Result<Vec<_>, PlotError>>()?;
    let table = rows
        .iter()
        .map(|r| {
            vec![
                r.skin.clone(),
                r.stripe_px.to_string(),
                format!("{:.2}", r.period_mm),
                format!("{:.2}", r.kernel_width_weighted_mm),
                format!("{:.2}", r.period_over_width),
                format!(
                    "{:.2} / {:.2} / {:.2}",
                    r.leak_mean[0], r.leak_mean[1], r.leak_mean[2]
                ),
                format!("{:.3}", r.kernel.global_rel_rmse),
                format!("{:.3}", r.nayar.global_rel_rmse),
                format!("{:.3}", r.kernel.direct_rel_rmse),
                format!("{:.3}", r.nayar.direct_rel_rmse),
            ]
        })
        .collect();
    let mut html = HtmlReport::new("Separation against stripe period / kernel width");
    html.heading("Separation error against the stripe period over the kernel's width")
        .paragraph(
            "One simulated head per skin type and stripe width, separated by the kernel-aware \
             method (ours) and by Nayar et al. (2006), scored against the simulator's truth \
             (relative RMS error over the face, all projectors and channels). Kernel width: \
             interquartile width of the base skin's Monte Carlo line spread at normal \
             incidence, channels weighted by their diffuse reflectance. Nayar's split needs a \
             period well below the kernel width (ratio << 1); the booth's stripes sit near or \
             above 1, where the global light follows the stripes.",
        )
        .figure("error against stripe period / kernel width", panels)
        .table(
            &[
                "type",
                "stripe (px)",
                "period (mm)",
                "kernel width (mm)",
                "period / width",
                "leak R/G/B",
                "global: ours",
                "global: Nayar",
                "direct: ours",
                "direct: Nayar",
            ],
            table,
        );
    Ok(html)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grid of a separable Gaussian kernel of sigma `sigma_mm` in every channel.
    fn gaussian_grid(sigma_mm: f64, cell_mm: f64, cells: usize) -> ResponseGrid {
        let c0 = (cells as f64 - 1.0) / 2.0;
        let g = |i: usize| (-((i as f64 - c0) * cell_mm).powi(2) / (2.0 * sigma_mm.powi(2))).exp();
        let values = (0..cells * cells)
            .map(|i| {
                let v = (g(i % cells) * g(i / cells)) as f32;
                [v, 0.5 * v, 0.25 * v]
            })
            .collect();
        ResponseGrid {
            cell_mm,
            cells,
            values,
        }
    }

    #[test]
    fn a_gaussian_kernel_has_the_interquartile_width_of_its_line_spread() {
        // The line spread of a 2-D Gaussian is the 1-D Gaussian of the same sigma, whose
        // interquartile range is 2 * 0.67449 sigma.
        let grid = gaussian_grid(1.5, 0.05, 401);
        let (widths, weighted) = line_spread_width_mm(&grid);
        for w in widths {
            assert!((w - 2.0 * 0.674_49 * 1.5).abs() < 0.01, "{w}");
        }
        assert!((weighted - widths[0]).abs() < 1e-9);
    }

    #[test]
    fn the_period_is_two_stripes_at_the_projectors_pitch() {
        let booth = Booth::builtin(true);
        let expected: f64 = booth
            .projectors
            .iter()
            .map(|p| {
                let d: f64 = (0..3)
                    .map(|i| (p.look_at_mm[i] - p.position_mm[i]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                6.0 * d / p.fx
            })
            .sum::<f64>()
            / booth.projectors.len() as f64;
        assert!((stripe_period_mm(&booth, 3) - expected).abs() < 1e-12);
    }

    #[test]
    fn an_empty_density_has_no_width() {
        assert_eq!(interquartile_width(&[0.0; 5]), 0.0);
        // All mass in one cell: quartiles at 0.25 and 0.75 of that cell.
        assert!((interquartile_width(&[0.0, 4.0, 0.0]) - 0.5).abs() < 1e-12);
    }
}
