//! A line plot for stage figures (e.g. the paper's Fig. 10 scanline), written as SVG (the HTML
//! report embeds it) and PNG. The stages describe their curves here; drawing is
//! [`crate::report::plot`]'s, the crate's one plotting stack, so both files look like every other
//! figure.
//!
//! Conventions: data coordinates are mapped linearly onto the plot area; y grows upwards and
//! starts at 0.

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

impl LinePlot {
    /// The plot as drawn by [`crate::report::plot`].
    pub fn raster(&self) -> Plot {
        let mut plot = Plot::new(&self.title, &self.x_label, &self.y_label);
        plot.width = WIDTH;
        plot.height = HEIGHT;
        plot.y_from_zero = true;
        plot.series = self
            .series
            .iter()
            .map(|s| PlotSeries {
                label: s.label.clone(),
                points: s.points.clone(),
                color: s.colour,
                style: match s.mark {
                    Mark::Line => Style::Line,
                    Mark::Dashed => Style::Dashed,
                    Mark::Dots => Style::Points,
                },
            })
            .collect();
        plot
    }

    /// The SVG text of the plot (`None` when no series has a finite point).
    pub fn svg(&self) -> Result<Option<String>, PlotError> {
        match self.raster().svg() {
            Ok(text) => Ok(Some(text)),
            Err(PlotError::NoData(_)) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Writes `<stem>.svg` and `<stem>.png`; neither when there is nothing to draw (e.g. no lit
    /// pixel on the scanline).
    pub fn write(&self, stem: &Path) -> Result<(), LinePlotError> {
        let Some(text) = self.svg()? else {
            return Ok(());
        };
        let svg = stem.with_extension("svg");
        mlsss_core::atomic_file::write_bytes_atomically(&svg, text)
            .map_err(|source| LinePlotError::Io { path: svg, source })?;
        self.raster().save_png(&stem.with_extension("png"))?;
        Ok(())
    }
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
                Series {
                    label: "dashed".into(),
                    colour: [0, 150, 0],
                    mark: Mark::Dashed,
                    points: vec![(0.0, 1.0), (1.0, 0.5)],
                },
            ],
        };
        let svg = plot.svg().unwrap().unwrap();
        assert!(
            svg.contains("rising") && svg.contains("t &lt;1&gt;"),
            "{svg}"
        );
        // One dot in the plot plus the legend's sample; the NaN point is dropped.
        assert_eq!(svg.matches("<circle").count(), 2, "{svg}");
        let img = plot.raster().render().unwrap();
        assert_eq!(img.dimensions(), (WIDTH, HEIGHT));
        let count = |c: [u8; 3]| img.pixels().filter(|p| p.0 == c).count();
        assert!(count([200, 0, 0]) > 500 && count([0, 0, 200]) > 20);
        // The dashed line has gaps: fewer pixels than a solid line of about the same length.
        assert!(count([0, 150, 0]) > 200 && count([0, 150, 0]) < count([200, 0, 0]));
    }

    #[test]
    fn nothing_to_draw_writes_no_file() {
        let dir = tempfile::tempdir().unwrap();
        let plot = LinePlot {
            title: "empty".into(),
            series: vec![Series {
                label: "nan".into(),
                colour: [0, 0, 0],
                mark: Mark::Line,
                points: vec![(f64::NAN, 0.0)],
            }],
            ..LinePlot::default()
        };
        plot.write(&dir.path().join("p")).unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
