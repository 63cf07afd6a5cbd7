//! The one plotting stack of the crate: line and scatter plots drawn with `plotters`, as PNG
//! (`plotters`' bitmap backend with the text of [`super::font::Raster`], encoded by `image`) or
//! SVG, text in the embedded DejaVu Sans. Every figure of the crate goes through [`Plot`].
//!
//! Conventions: axes are linear; the x range is the data's widened by 3 % on each side, the y range
//! the data's widened by 5 % (from 0 when [`Plot::y_from_zero`]); non-finite points are dropped.
//! Image pixel (0, 0) is the top-left corner. The legend goes in whichever corner of the plot area
//! covers the fewest data points.

use std::io::Cursor;
use std::path::{Path, PathBuf};

use image::{ImageFormat, RgbImage};
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::element::MultiLineText;
use plotters::prelude::*;

use super::font::{self as embedded, FAMILY, Raster};

/// Errors of plot rendering.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PlotError {
    /// No series holds a finite point (nothing to scale the axes to).
    #[error("plot `{0}` has no finite data point")]
    NoData(String),
    /// `plotters` failed to draw (a font or backend error).
    #[error("drawing plot `{title}`: {message}")]
    Draw { title: String, message: String },
    /// The PNG could not be encoded.
    #[error("{path}: {source}")]
    Png {
        path: PathBuf,
        source: image::ImageError,
    },
    /// The PNG file could not be written.
    #[error(transparent)]
    File(#[from] mlsss_core::imageio::ImageIoError),
    /// The SVG could not be written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Connected line.
    Line,
    /// Dashed connected line.
    Dashed,
    /// A dot per point.
    Points,
    /// A line with a dot on each point.
    LineAndPoints,
}

/// One data series.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend text; an empty label keeps the series out of the legend.
    pub label: String,
    pub points: Vec<(f64, f64)>,
    pub color: [u8; 3],
    pub style: Style,
}

/// A plot: axes, series, labels.
#[derive(Debug, Clone, PartialEq)]
pub struct Plot {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    pub width: u32,
    pub height: u32,
    /// The y axis starts at 0 (or below, for negative data): radiance and profile plots.
    pub y_from_zero: bool,
}

/// Colours that stay apart on white, for series in order.
pub const PALETTE: [[u8; 3]; 6] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [255, 127, 14],
    [148, 103, 189],
    [90, 90, 90],
];

const TITLE_PX: f64 = 20.0;
const AXIS_DESC_PX: f64 = 15.0;
const TICK_PX: f64 = 13.0;
const LEGEND_PX: f64 = 13.0;
/// Left of the y tick labels: room for the rotated y label.
const Y_LABEL_AREA: u32 = 72;
const X_LABEL_AREA: u32 = 48;
const MARGIN: u32 = 14;
const GRID: RGBColor = RGBColor(225, 225, 225);
const LINE_WIDTH: u32 = 2;
const DOT_RADIUS: i32 = 3;

fn font(px: f64) -> FontDesc<'static> {
    (FAMILY, px).into_font()
}

/// The axis ranges of the plot's finite data: `(x0, x1, y0, y1)`.
fn ranges(plot: &Plot) -> Option<(f64, f64, f64, f64)> {
    let mut range = None::<(f64, f64, f64, f64)>;
    for (x, y) in plot.finite_points() {
        range = Some(match range {
            None => (x, x, y, y),
            Some((a, b, c, d)) => (a.min(x), b.max(x), c.min(y), d.max(y)),
        });
    }
    let (x0, x1, mut y0, y1) = range?;
    let (x0, x1) = padded(x0, x1, 0.03);
    if plot.y_from_zero {
        y0 = y0.min(0.0);
    }
    let (py0, y1) = padded(y0, y1, 0.05);
    let y0 = if plot.y_from_zero && y0 == 0.0 {
        0.0
    } else {
        py0
    };
    Some((x0, x1, y0, y1))
}

impl Plot {
    /// An empty 640x400 plot.
    pub fn new(title: &str, x_label: &str, y_label: &str) -> Self {
        Self {
            title: title.to_owned(),
            x_label: x_label.to_owned(),
            y_label: y_label.to_owned(),
            series: Vec::new(),
            width: 640,
            height: 400,
            y_from_zero: false,
        }
    }

    /// Adds a series with the next palette colour.
    pub fn with_series(mut self, label: &str, points: Vec<(f64, f64)>, style: Style) -> Self {
        let color = PALETTE[self.series.len() % PALETTE.len()];
        self.series.push(Series {
            label: label.to_owned(),
            points,
            color,
            style,
        });
        self
    }

    fn finite_points(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        self.series.iter().flat_map(|s| finite(&s.points))
    }

    fn draw_error(&self, e: impl std::fmt::Display) -> PlotError {
        PlotError::Draw {
            title: self.title.clone(),
            message: e.to_string(),
        }
    }

    /// Draws the plot onto a backend's root area; returns where the legend went (none without
    /// labelled series).
    fn draw<'r, DB: DrawingBackend + 'r>(
        &self,
        root: &'r DrawingArea<DB, Shift>,
    ) -> Result<Option<SeriesLabelPosition>, PlotError> {
        let (x0, x1, y0, y1) = ranges(self).ok_or_else(|| PlotError::NoData(self.title.clone()))?;
        embedded::register();
        let err = |e: DrawingAreaErrorKind<DB::ErrorType>| self.draw_error(e);
        root.fill(&WHITE).map_err(err)?;
        let mut chart = ChartBuilder::on(root)
            .caption(&self.title, font(TITLE_PX))
            .margin(MARGIN)
            .x_label_area_size(X_LABEL_AREA)
            .y_label_area_size(Y_LABEL_AREA)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(&self.x_label)
            .y_desc(&self.y_label)
            .axis_desc_style(font(AXIS_DESC_PX))
            .label_style(font(TICK_PX))
            .x_labels(10)
            .y_labels(10)
            .x_label_formatter(&|v| tick_label(*v))
            .y_label_formatter(&|v| tick_label(*v))
            .bold_line_style(GRID)
            .light_line_style(TRANSPARENT)
            .axis_style(BLACK)
            .draw()
            .map_err(err)?;
        for s in &self.series {
            let color = RGBColor(s.color[0], s.color[1], s.color[2]);
            let line = color.stroke_width(LINE_WIDTH);
            let pts: Vec<(f64, f64)> = finite(&s.points).collect();
            let anno = match s.style {
                Style::Line | Style::LineAndPoints => chart
                    .draw_series(LineSeries::new(pts.iter().copied(), line))
                    .map_err(err)?,
                Style::Dashed => chart
                    .draw_series(DashedLineSeries::new(pts.iter().copied(), 7, 4, line))
                    .map_err(err)?,
                Style::Points => chart
                    .draw_series(
                        pts.iter()
                            .map(|&p| Circle::new(p, DOT_RADIUS, color.filled())),
                    )
                    .map_err(err)?,
            };
            if !s.label.is_empty() {
                // One element type for every style: the parts a style lacks are transparent (no
                // backend draws those).
                let (a, b, dot) = legend_parts(s.style);
                let none = ShapeStyle::from(&TRANSPARENT);
                let piece = move |span: Option<(i32, i32)>| {
                    let (x0, x1) = span.unwrap_or((0, 0));
                    PathElement::new(
                        vec![(x0, 0), (x1, 0)],
                        if span.is_some() { line } else { none },
                    )
                };
                let dot = if dot { color.filled() } else { none };
                anno.label(&s.label).legend(move |(x, y)| {
                    EmptyElement::at((x, y))
                        + piece(a)
                        + piece(b)
                        + Circle::new((10, 0), DOT_RADIUS, dot)
                });
            }
            if s.style == Style::LineAndPoints {
                chart
                    .draw_series(
                        pts.iter()
                            .map(|&p| Circle::new(p, DOT_RADIUS, color.filled())),
                    )
                    .map_err(err)?;
            }
        }
        let mut legend = None;
        if self.series.iter().any(|s| !s.label.is_empty()) {
            let position = self.legend_position(&chart)?;
            legend = Some(position.clone());
            chart
                .configure_series_labels()
                .position(position)
                .label_font(font(LEGEND_PX))
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK.mix(0.4))
                .draw()
                .map_err(err)?;
        }
        root.present().map_err(err)?;
        Ok(legend)
    }

    /// The upper or lower corner (or middle) of the plot area where the legend box covers the
    /// fewest data points and line pieces; the upper right on a tie.
    fn legend_position<DB: DrawingBackend>(
        &self,
        chart: &ChartContext<DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    ) -> Result<SeriesLabelPosition, PlotError> {
        let style = font(LEGEND_PX).into_text_style(chart.plotting_area());
        let mut text = MultiLineText::<_, &str>::new((0, 0), &style);
        for s in self.series.iter().filter(|s| !s.label.is_empty()) {
            text.push_line(s.label.as_str());
        }
        let (w, h) = text.estimate_dimension().map_err(|e| self.draw_error(e))?;
        // The box plotters draws: 30 px for the marks, 10 px margins (see SeriesLabelStyle).
        let (w, h) = (w + 30 + 20, h + 20);
        let (area_w, area_h) = chart.plotting_area().dim_in_pixel();
        let (area_w, area_h) = (area_w as i32, area_h as i32);
        let base = chart.plotting_area().get_base_pixel();
        let samples: Vec<(i32, i32)> = self
            .series
            .iter()
            .flat_map(|s| {
                let pts: Vec<(i32, i32)> = finite(&s.points)
                    .map(|p| {
                        let (x, y) = chart.backend_coord(&p);
                        (x - base.0, y - base.1)
                    })
                    .collect();
                let lines = s.style != Style::Points;
                let mut out = pts.clone();
                if lines {
                    // A few samples along each segment, so long lines count too.
                    for w in pts.windows(2) {
                        for k in 1..4 {
                            let t = f64::from(k) / 4.0;
                            out.push((
                                w[0].0 + (f64::from(w[1].0 - w[0].0) * t) as i32,
                                w[0].1 + (f64::from(w[1].1 - w[0].1) * t) as i32,
                            ));
                        }
                    }
                }
                out
            })
            .collect();
        use SeriesLabelPosition as P;
        let candidates = [
            (P::UpperRight, area_w - w - 5, 5),
            (P::UpperLeft, 5, 5),
            (P::LowerRight, area_w - w - 5, area_h - h - 5),
            (P::LowerLeft, 5, area_h - h - 5),
            (P::UpperMiddle, (area_w - w) / 2, 5),
            (P::LowerMiddle, (area_w - w) / 2, area_h - h - 5),
        ];
        let covered = |x: i32, y: i32| {
            samples
                .iter()
                .filter(|p| p.0 >= x - 4 && p.0 <= x + w + 4 && p.1 >= y - 4 && p.1 <= y + h + 4)
                .count()
        };
        let best = candidates
            .into_iter()
            .map(|(pos, x, y)| (covered(x, y), pos))
            .min_by_key(|(n, _)| *n)
            .map_or(P::UpperRight, |(_, pos)| pos);
        Ok(best)
    }

    /// Renders the plot.
    pub fn render(&self) -> Result<RgbImage, PlotError> {
        let mut buf = vec![0u8; self.width as usize * self.height as usize * 3];
        {
            let root = Raster::with_buffer(&mut buf, (self.width, self.height)).into_drawing_area();
            self.draw(&root)?;
        }
        RgbImage::from_raw(self.width, self.height, buf)
            .ok_or_else(|| self.draw_error("pixel buffer of the wrong size"))
    }

    /// The plot as SVG text (same layout as the PNG; text names the `sans-serif` family).
    pub fn svg(&self) -> Result<String, PlotError> {
        let mut text = String::new();
        {
            let root =
                SVGBackend::with_string(&mut text, (self.width, self.height)).into_drawing_area();
            self.draw(&root)?;
        }
        Ok(text)
    }

    /// PNG bytes of the plot.
    pub fn png_bytes(&self) -> Result<Vec<u8>, PlotError> {
        let img = self.render()?;
        let mut bytes = Vec::new();
        img.write_to(&mut Cursor::new(&mut bytes), ImageFormat::Png)
            .map_err(|source| PlotError::Png {
                path: PathBuf::from("<memory>"),
                source,
            })?;
        Ok(bytes)
    }

    /// Writes the plot as a PNG file.
    pub fn save_png(&self, path: &Path) -> Result<(), PlotError> {
        Ok(mlsss_core::imageio::write_png(path, &self.render()?)?)
    }

    /// Writes the plot as an SVG file.
    pub fn save_svg(&self, path: &Path) -> Result<(), PlotError> {
        mlsss_core::atomic_file::write_bytes_atomically(path, self.svg()?).map_err(|source| {
            PlotError::Io {
                path: path.to_owned(),
                source,
            }
        })
    }
}

/// The finite points of a series, in order.
fn finite(points: &[(f64, f64)]) -> impl Iterator<Item = (f64, f64)> + '_ {
    points
        .iter()
        .copied()
        .filter(|(x, y)| x.is_finite() && y.is_finite())
}

/// The legend's sample of a series, relative to its left end: two line pieces (`(x0, x1)` pixel
/// spans, `None` when absent) and whether a dot sits in the middle.
type LegendParts = (Option<(i32, i32)>, Option<(i32, i32)>, bool);

fn legend_parts(style: Style) -> LegendParts {
    match style {
        Style::Line => (Some((0, 20)), None, false),
        Style::Dashed => (Some((0, 7)), Some((12, 20)), false),
        Style::Points => (None, None, true),
        Style::LineAndPoints => (Some((0, 20)), None, true),
    }
}

/// The range widened by `frac` of its span on each side (and made non-empty).
fn padded(lo: f64, hi: f64, frac: f64) -> (f64, f64) {
    let span = hi - lo;
    if span <= f64::EPSILON * hi.abs().max(1.0) {
        let d = if lo == 0.0 { 1.0 } else { 0.1 * lo.abs() };
        return (lo - d, hi + d);
    }
    (lo - frac * span, hi + frac * span)
}

/// A short label for a tick value: at most 3 significant digits, trailing zeros trimmed.
fn tick_label(v: f64) -> String {
    let a = v.abs();
    if a < 1e-12 {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.0e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else {
        let decimals = (2 - a.log10().floor() as i32).clamp(0, 6) as usize;
        let s = format!("{v:.decimals$}");
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_owned()
        } else {
            s
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn count(img: &RgbImage, c: [u8; 3]) -> usize {
        img.pixels().filter(|p| p.0 == c).count()
    }

    #[test]
    fn tick_labels_are_short() {
        assert_eq!(tick_label(0.30000000000000004), "0.3");
        assert_eq!(tick_label(1500.0), "1500");
        assert_eq!(tick_label(-0.0125), "-0.0125");
        assert_eq!(tick_label(1e-17), "0");
        assert_eq!(tick_label(2e6), "2e6");
    }

    #[test]
    fn text_is_drawn() {
        // A single invisible-in-the-legend point: the title band holds only text.
        let plot = Plot::new("Title", "x", "y").with_series("", vec![(0.0, 0.0)], Style::Points);
        let img = plot.render().unwrap();
        let dark = (0..30u32)
            .flat_map(|y| (0..img.width()).map(move |x| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y).0[0] < 128)
            .count();
        assert!(dark > 50, "the title is drawn ({dark} dark pixels)");
    }

    #[test]
    fn series_land_where_the_data_says() {
        // A rising line and a single point, each in its own colour, on a 640x400 canvas.
        let plot = Plot::new("t", "x", "y")
            .with_series("line", vec![(0.0, 0.0), (10.0, 1.0)], Style::Line)
            .with_series("pt", vec![(10.0, 0.0)], Style::Points);
        let img = plot.render().unwrap();
        assert_eq!(img.dimensions(), (640, 400));
        // Pixels of exactly one colour.
        let where_is = |c: [u8; 3]| -> Vec<(u32, u32)> {
            img.enumerate_pixels()
                .filter(|p| p.2.0 == c)
                .map(|p| (p.0, p.1))
                .collect()
        };
        // The line runs from the lower left to the upper right of the plot area (the legend
        // sample adds a few pixels of the same colour at the top left).
        let line = where_is(PALETTE[0]);
        let lowest_left = line.iter().filter(|p| p.0 < 200).map(|p| p.1).max();
        let highest_right = line.iter().filter(|p| p.0 > 450).map(|p| p.1).min();
        assert!(lowest_left > Some(300), "{lowest_left:?}");
        assert!(highest_right < Some(100), "{highest_right:?}");
        // The point sits at the lower right; its only other pixels are the legend's sample.
        let dot = where_is(PALETTE[1]);
        let plotted: Vec<&(u32, u32)> = dot.iter().filter(|p| p.0 > 560).collect();
        assert!(
            plotted.len() > 20 && plotted.iter().all(|p| p.1 > 300),
            "{plotted:?}"
        );
        assert!(dot.iter().all(|p| p.0 > 560 || p.1 < 150), "{dot:?}");
        let png = plot.png_bytes().unwrap();
        assert_eq!(&png[1..4], b"PNG");
    }

    #[test]
    fn the_legend_names_every_labelled_series_and_avoids_the_data() {
        // Data crowding the upper right: the legend moves elsewhere.
        let pts: Vec<(f64, f64)> = (0..50).map(|i| (f64::from(i), f64::from(i))).collect();
        let plot = Plot::new("t", "x", "y").with_series("diagonal", pts, Style::Points);
        let img = plot.render().unwrap();
        // The legend box is white; the series dots inside it would show through otherwise.
        let svg = plot.svg().unwrap();
        for text in ["diagonal", "t", "x", "y"] {
            assert!(
                svg.contains(&format!(">\n{text}\n</text>")),
                "{text} in the SVG"
            );
        }
        assert!(count(&img, PALETTE[0]) > 50 * 20);
        let mut buf = String::new();
        let root = SVGBackend::with_string(&mut buf, (640, 400)).into_drawing_area();
        let pos = plot.draw(&root).unwrap();
        assert!(
            matches!(
                pos,
                Some(SeriesLabelPosition::UpperLeft | SeriesLabelPosition::LowerRight)
            ),
            "{pos:?}"
        );
    }

    #[test]
    fn y_from_zero_starts_the_axis_at_zero() {
        let mut plot =
            Plot::new("t", "x", "y").with_series("", vec![(0.0, 5.0), (1.0, 6.0)], Style::Line);
        assert!(ranges(&plot).unwrap().2 > 4.0);
        plot.y_from_zero = true;
        assert_eq!(ranges(&plot).unwrap().2, 0.0);
    }

    #[test]
    fn empty_data_is_an_error() {
        let empty = Plot::new("e", "x", "y").with_series("s", vec![(f64::NAN, 1.0)], Style::Line);
        assert!(matches!(empty.render(), Err(PlotError::NoData(_))));
        assert!(matches!(empty.svg(), Err(PlotError::NoData(_))));
    }
}
