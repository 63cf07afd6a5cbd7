//! A line plot for stage figures (e.g. the paper's Fig. 10 scanline), written as SVG (axes,
//! labels, legend, dashed truth curves; the HTML report embeds it) and as PNG through
//! [`crate::report::plot`]. No plotting dependency: the figures are simple and build offline.
//!
//! Conventions: data coordinates are mapped linearly onto the plot area; y grows upwards.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::report::plot::{Plot, PlotError, Series as PlotSeries, Style};

/// Errors writing a plot.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LinePlotError {
    /// The SVG could not be written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The PNG could not be drawn or written.
    #[error(transparent)]
    Png(#[from] PlotError),
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mark {
    /// Connected line.
    Line,
    /// Dashed line.
    Dashed,
    /// A dot per point.
    Dots,
}

/// One curve.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub label: String,
    pub colour: [u8; 3],
    pub mark: Mark,
    pub points: Vec<(f64, f64)>,
}

/// A plot: title, axis labels, curves.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LinePlot {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
}

const WIDTH: u32 = 800;
const HEIGHT: u32 = 450;
const MARGIN: (f64, f64, f64, f64) = (70.0, 20.0, 40.0, 50.0); // left, right, top, bottom

impl LinePlot {
    /// Data bounds over every finite point (a 1-unit range when empty or flat).
    fn bounds(&self) -> (f64, f64, f64, f64) {
        let pts = self
            .series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|p| p.0.is_finite() && p.1.is_finite());
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in pts {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
        if x0 > x1 {
            return (0.0, 1.0, 0.0, 1.0);
        }
        if x1 - x0 < 1e-12 {
            x1 = x0 + 1.0;
        }
        y0 = y0.min(0.0);
        if y1 - y0 < 1e-12 {
            y1 = y0 + 1.0;
        }
        (x0, x1, y0, y1 + 0.05 * (y1 - y0))
    }

    fn mapper(&self) -> impl Fn(f64, f64) -> (f64, f64) {
        let (x0, x1, y0, y1) = self.bounds();
        let (l, r, t, b) = MARGIN;
        let (w, h) = (f64::from(WIDTH) - l - r, f64::from(HEIGHT) - t - b);
        move |x, y| {
            (
                l + (x - x0) / (x1 - x0) * w,
                t + (1.0 - (y - y0) / (y1 - y0)) * h,
            )
        }
    }

    /// The SVG text of the plot.
    pub fn svg(&self) -> String {
        let (x0, x1, y0, y1) = self.bounds();
        let map = self.mapper();
        let (l, r, t, b) = MARGIN;
        let (right, bottom) = (f64::from(WIDTH) - r, f64::from(HEIGHT) - b);
        let mut s = String::new();
        let _ = writeln!(
            s,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" font-family="sans-serif" font-size="12">"#
        );
        let _ = writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
        let _ = writeln!(
            s,
            r#"<text x="{}" y="20" text-anchor="middle" font-size="14">{}</text>"#,
            f64::from(WIDTH) / 2.0,
            escape(&self.title)
        );
        let _ = writeln!(
            s,
            r#"<polyline points="{l},{t} {l},{bottom} {right},{bottom}" fill="none" stroke="black"/>"#
        );
        for k in 0..=4 {
            let fx = x0 + (x1 - x0) * f64::from(k) / 4.0;
            let fy = y0 + (y1 - y0) * f64::from(k) / 4.0;
            let (px, _) = map(fx, y0);
            let (_, py) = map(x0, fy);
            let _ = writeln!(
                s,
                r#"<text x="{px:.1}" y="{:.1}" text-anchor="middle">{}</text>"#,
                bottom + 16.0,
                tick(fx)
            );
            let _ = writeln!(
                s,
                r#"<text x="{:.1}" y="{:.1}" text-anchor="end">{}</text>"#,
                l - 6.0,
                py + 4.0,
                tick(fy)
            );
        }
        let _ = writeln!(
            s,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">{}</text>"#,
            (l + right) / 2.0,
            f64::from(HEIGHT) - 10.0,
            escape(&self.x_label)
        );
        let _ = writeln!(
            s,
            r#"<text x="14" y="{:.1}" text-anchor="middle" transform="rotate(-90 14 {:.1})">{}</text>"#,
            (t + bottom) / 2.0,
            (t + bottom) / 2.0,
            escape(&self.y_label)
        );
        for (k, series) in self.series.iter().enumerate() {
            let colour = format!(
                "rgb({},{},{})",
                series.colour[0], series.colour[1], series.colour[2]
            );
            let pts: Vec<(f64, f64)> = series
                .points
                .iter()
                .filter(|p| p.0.is_finite() && p.1.is_finite())
                .map(|&(x, y)| map(x, y))
                .collect();
            match series.mark {
                Mark::Dots => {
                    for (x, y) in &pts {
                        let _ = writeln!(
                            s,
                            r#"<circle cx="{x:.1}" cy="{y:.1}" r="2.5" fill="{colour}"/>"#
                        );
                    }
                }
                Mark::Line | Mark::Dashed => {
                    let list: Vec<String> =
                        pts.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
                    let dash = if series.mark == Mark::Dashed {
                        r#" stroke-dasharray="6 4""#
                    } else {
                        ""
                    };
                    let _ = writeln!(
                        s,
                        r#"<polyline points="{}" fill="none" stroke="{colour}" stroke-width="1.5"{dash}/>"#,
                        list.join(" ")
                    );
                }
            }
            let ly = t + 14.0 + 16.0 * k as f64;
            let _ = writeln!(
                s,
                r#"<rect x="{:.1}" y="{:.1}" width="14" height="4" fill="{colour}"/><text x="{:.1}" y="{:.1}">{}</text>"#,
                right - 190.0,
                ly - 6.0,
                right - 170.0,
                ly,
                escape(&series.label)
            );
        }
        s.push_str("</svg>\n");
        s
    }

    /// The same plot as a PNG, drawn by [`crate::report::plot`] (its font and axes; dashed
    /// curves become solid lines).
    pub fn raster(&self) -> Plot {
        let mut plot = Plot::new(&self.title, &self.x_label, &self.y_label);
        plot.width = WIDTH;
        plot.height = HEIGHT;
        plot.series = self
            .series
            .iter()
            .map(|s| PlotSeries {
                label: s.label.clone(),
                points: s.points.clone(),
                color: s.colour,
                style: match s.mark {
                    Mark::Line | Mark::Dashed => Style::Line,
                    Mark::Dots => Style::Points,
                },
            })
            .collect();
        plot
    }

    /// Writes `<stem>.svg` and `<stem>.png`.
    pub fn write(&self, stem: &Path) -> Result<(), LinePlotError> {
        let svg = stem.with_extension("svg");
        std::fs::write(&svg, self.svg())
            .map_err(|source| LinePlotError::Io { path: svg, source })?;
        match self.raster().save_png(&stem.with_extension("png")) {
            // Nothing to draw (e.g. no lit pixel on the scanline): the SVG says so, no PNG.
            Err(PlotError::NoData(_)) => Ok(()),
            other => other.map_err(LinePlotError::Png),
        }
    }
}

fn tick(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v.abs() >= 100.0 || v.abs() < 0.01 {
        format!("{v:.2e}")
    } else {
        format!("{v:.3}")
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_each_series_in_its_colour_and_labels_it() {
        let plot = LinePlot {
            title: "t <1>".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            series: vec![
                Series {
                    label: "rising".into(),
                    colour: [200, 0, 0],
                    mark: Mark::Line,
                    points: vec![(0.0, 0.0), (1.0, 1.0)],
                },
                Series {
                    label: "dots".into(),
                    colour: [0, 0, 200],
                    mark: Mark::Dots,
                    points: vec![(0.5, 0.2), (f64::NAN, 1.0)],
                },
            ],
        };
        let svg = plot.svg();
        assert!(svg.contains("rising") && svg.contains("t &lt;1&gt;"));
        assert_eq!(svg.matches("<circle").count(), 1, "NaN points are dropped");
        let img = plot.raster().render().unwrap();
        let count = |c: [u8; 3]| img.pixels().filter(|p| p.0 == c).count();
        assert!(count([200, 0, 0]) > 100 && count([0, 0, 200]) > 5);
    }
}
