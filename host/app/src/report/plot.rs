//! Line and scatter plots rendered to PNG with the `image` crate and the built-in bitmap font.
//!
//! Conventions: data coordinates are mapped linearly (or log10 on an axis marked `log`) into a
//! plot frame; image pixel (0, 0) is the top-left corner. Ticks are at 1, 2 or 5 x 10^k steps.

use std::io::Cursor;
use std::path::{Path, PathBuf};

use image::{ImageFormat, Rgb, RgbImage};

use super::font;

/// Errors of plot rendering.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PlotError {
    /// No series holds a finite point (nothing to scale the axes to).
    #[error("plot `{0}` has no finite data point")]
    NoData(String),
    /// A log axis got a non-positive value.
    #[error("plot `{0}`: a logarithmic axis needs positive values")]
    NonPositiveOnLogAxis(String),
    /// The PNG could not be encoded or written.
    #[error("{path}: {source}")]
    Png {
        path: PathBuf,
        source: image::ImageError,
    },
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    Line,
    Points,
    LineAndPoints,
}

/// One data series.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
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
    pub log_x: bool,
    pub log_y: bool,
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

const MARGIN_LEFT: u32 = 78;
const MARGIN_RIGHT: u32 = 16;
const MARGIN_TOP: u32 = 34;
const MARGIN_BOTTOM: u32 = 52;
const WHITE: Rgb<u8> = Rgb([255, 255, 255]);
const BLACK: Rgb<u8> = Rgb([0, 0, 0]);
const GRID: Rgb<u8> = Rgb([225, 225, 225]);

impl Plot {
    /// An empty 640x400 linear plot.
    pub fn new(title: &str, x_label: &str, y_label: &str) -> Self {
        Self {
            title: title.to_owned(),
            x_label: x_label.to_owned(),
            y_label: y_label.to_owned(),
            series: Vec::new(),
            width: 640,
            height: 400,
            log_x: false,
            log_y: false,
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
        self.series
            .iter()
            .flat_map(|s| s.points.iter().copied())
            .filter(|(x, y)| x.is_finite() && y.is_finite())
    }

    /// Renders the plot.
    pub fn render(&self) -> Result<RgbImage, PlotError> {
        let to_axis = |v: f64, log: bool| if log { v.log10() } else { v };
        let mut range = None::<(f64, f64, f64, f64)>;
        for (x, y) in self.finite_points() {
            if (self.log_x && x <= 0.0) || (self.log_y && y <= 0.0) {
                return Err(PlotError::NonPositiveOnLogAxis(self.title.clone()));
            }
            let (x, y) = (to_axis(x, self.log_x), to_axis(y, self.log_y));
            range = Some(match range {
                None => (x, x, y, y),
                Some((a, b, c, d)) => (a.min(x), b.max(x), c.min(y), d.max(y)),
            });
        }
        let (x0, x1, y0, y1) = range.ok_or_else(|| PlotError::NoData(self.title.clone()))?;
        let (x0, x1) = padded(x0, x1);
        let (y0, y1) = padded(y0, y1);
        let mut img = RgbImage::from_pixel(self.width, self.height, WHITE);
        let frame = Frame {
            left: MARGIN_LEFT as f64,
            right: (self.width - MARGIN_RIGHT) as f64,
            top: MARGIN_TOP as f64,
            bottom: (self.height - MARGIN_BOTTOM) as f64,
            x0,
            x1,
            y0,
            y1,
        };
        self.draw_axes(&mut img, &frame);
        for s in &self.series {
            let pts: Vec<(f64, f64)> = s
                .points
                .iter()
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .map(|&(x, y)| frame.to_pixel(to_axis(x, self.log_x), to_axis(y, self.log_y)))
                .collect();
            let color = Rgb(s.color);
            if matches!(s.style, Style::Line | Style::LineAndPoints) {
                for w in pts.windows(2) {
                    draw_line(&mut img, w[0], w[1], color);
                }
            }
            if matches!(s.style, Style::Points | Style::LineAndPoints) {
                for &p in &pts {
                    draw_marker(&mut img, p, color);
                }
            }
        }
        self.draw_legend(&mut img, &frame);
        Ok(img)
    }

    fn draw_axes(&self, img: &mut RgbImage, f: &Frame) {
        for (v, major) in ticks(f.x0, f.x1) {
            let (px, _) = f.to_pixel(v, f.y0);
            vline(img, px, f.top, f.bottom, GRID);
            let label = tick_label(v, major, self.log_x);
            let (w, _) = font::text_size(&label, 1);
            draw_text(
                img,
                &label,
                px as i64 - i64::from(w) / 2,
                f.bottom as i64 + 6,
                BLACK,
                1,
            );
        }
        for (v, major) in ticks(f.y0, f.y1) {
            let (_, py) = f.to_pixel(f.x0, v);
            hline(img, f.left, f.right, py, GRID);
            let label = tick_label(v, major, self.log_y);
            let (w, h) = font::text_size(&label, 1);
            draw_text(
                img,
                &label,
                f.left as i64 - 6 - i64::from(w),
                py as i64 - i64::from(h) / 2,
                BLACK,
                1,
            );
        }
        hline(img, f.left, f.right, f.bottom, BLACK);
        hline(img, f.left, f.right, f.top, BLACK);
        vline(img, f.left, f.top, f.bottom, BLACK);
        vline(img, f.right, f.top, f.bottom, BLACK);
        let (tw, _) = font::text_size(&self.title, 2);
        draw_text(
            img,
            &self.title,
            (self.width as i64 - i64::from(tw)) / 2,
            8,
            BLACK,
            2,
        );
        let (xw, _) = font::text_size(&self.x_label, 1);
        let xc = (f.left + f.right) / 2.0;
        draw_text(
            img,
            &self.x_label,
            xc as i64 - i64::from(xw) / 2,
            self.height as i64 - 20,
            BLACK,
            1,
        );
        // The y label reads top to bottom, one character per line, left of the tick labels.
        let yc = (f.top + f.bottom) / 2.0;
        let n = self.y_label.chars().count() as i64;
        let y_start = yc as i64 - n * i64::from(font::CELL_HEIGHT) / 2;
        for (i, c) in self.y_label.chars().enumerate() {
            let y = y_start + i as i64 * i64::from(font::CELL_HEIGHT);
            draw_text(img, &c.to_string(), 4, y, BLACK, 1);
        }
    }

    fn draw_legend(&self, img: &mut RgbImage, f: &Frame) {
        let mut y = f.top as i64 + 8;
        for s in self.series.iter().filter(|s| !s.label.is_empty()) {
            let (w, _) = font::text_size(&s.label, 1);
            let x = f.right as i64 - 30 - i64::from(w);
            fill_rect(img, x - 4, y - 3, i64::from(w) + 32, 14, WHITE);
            let color = Rgb(s.color);
            draw_line(
                img,
                (x as f64, y as f64 + 3.5),
                (x as f64 + 18.0, y as f64 + 3.5),
                color,
            );
            if s.style != Style::Line {
                draw_marker(img, (x as f64 + 9.0, y as f64 + 3.5), color);
            }
            draw_text(img, &s.label, x + 24, y, BLACK, 1);
            y += 14;
        }
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
        self.render()?
            .save_with_format(path, ImageFormat::Png)
            .map_err(|source| PlotError::Png {
                path: path.to_owned(),
                source,
            })
    }
}

/// The data-to-pixel map of the plot frame.
struct Frame {
    left: f64,
    right: f64,
    top: f64,
    bottom: f64,
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
}

impl Frame {
    fn to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        let u = (x - self.x0) / (self.x1 - self.x0);
        let v = (y - self.y0) / (self.y1 - self.y0);
        (
            self.left + u * (self.right - self.left),
            self.bottom - v * (self.bottom - self.top),
        )
    }
}

/// The range widened by 5 % on each side (and made non-empty).
fn padded(lo: f64, hi: f64) -> (f64, f64) {
    let span = hi - lo;
    if span <= f64::EPSILON * hi.abs().max(1.0) {
        let d = if lo == 0.0 { 1.0 } else { 0.1 * lo.abs() };
        return (lo - d, hi + d);
    }
    (lo - 0.05 * span, hi + 0.05 * span)
}

/// Tick positions in `[lo, hi]` at a 1/2/5 x 10^k step giving at most 8 ticks; `true` marks every
/// tick (all are labelled).
pub fn ticks(lo: f64, hi: f64) -> Vec<(f64, bool)> {
    let span = hi - lo;
    if !(span > 0.0 && span.is_finite()) {
        return Vec::new();
    }
    let raw = span / 6.0;
    let magnitude = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * magnitude)
        .find(|s| span / s <= 7.0)
        .unwrap_or(10.0 * magnitude);
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    (first..=last).map(|i| (i as f64 * step, true)).collect()
}

/// A short label for a tick value (`log` axes show 10^v).
fn tick_label(v: f64, _major: bool, log: bool) -> String {
    let v = if log { 10f64.powf(v) } else { v };
    let a = v.abs();
    if a == 0.0 || a < 1e-12 {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.0e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else {
        // Enough decimals for 3 significant digits, trailing zeros trimmed.
        let decimals = (2 - a.log10().floor() as i32).clamp(0, 6) as usize;
        let s = format!("{v:.decimals$}");
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_owned()
        } else {
            s
        }
    }
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, c);
    }
}

fn fill_rect(img: &mut RgbImage, x: i64, y: i64, w: i64, h: i64, c: Rgb<u8>) {
    for yy in y..y + h {
        for xx in x..x + w {
            put(img, xx, yy, c);
        }
    }
}

fn hline(img: &mut RgbImage, x0: f64, x1: f64, y: f64, c: Rgb<u8>) {
    for x in x0.round() as i64..=x1.round() as i64 {
        put(img, x, y.round() as i64, c);
    }
}

fn vline(img: &mut RgbImage, x: f64, y0: f64, y1: f64, c: Rgb<u8>) {
    for y in y0.round() as i64..=y1.round() as i64 {
        put(img, x.round() as i64, y, c);
    }
}

/// A 2-px wide line (DDA: one step per pixel along the longer axis).
fn draw_line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), c: Rgb<u8>) {
    let steps = (b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil().max(1.0) as i64;
    for i in 0..=steps {
        let t = i as f64 / steps as f64;
        let x = (a.0 + t * (b.0 - a.0)).round() as i64;
        let y = (a.1 + t * (b.1 - a.1)).round() as i64;
        put(img, x, y, c);
        put(img, x + 1, y, c);
        put(img, x, y + 1, c);
    }
}

/// A filled 5x5 square marker.
fn draw_marker(img: &mut RgbImage, p: (f64, f64), c: Rgb<u8>) {
    fill_rect(img, p.0.round() as i64 - 2, p.1.round() as i64 - 2, 5, 5, c);
}

/// Draws `text` with its top-left corner at `(x, y)`.
pub fn draw_text(img: &mut RgbImage, text: &str, x: i64, y: i64, c: Rgb<u8>, scale: u32) {
    for (dx, dy) in font::ink(text, scale) {
        put(img, x + i64::from(dx), y + i64::from(dy), c);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_numbers_inside_the_range() {
        let t: Vec<f64> = ticks(0.0, 1.0).into_iter().map(|t| t.0).collect();
        assert_eq!(t.len(), 6, "{t:?}");
        for (v, want) in t.iter().zip([0.0, 0.2, 0.4, 0.6, 0.8, 1.0]) {
            assert!((v - want).abs() < 1e-12, "{t:?}");
        }
        let t = ticks(-3.2, 17.9);
        assert!(t.len() >= 4 && t.len() <= 11, "{t:?}");
        assert!(t.iter().all(|(v, _)| (-3.2..=17.9).contains(v)));
        assert_eq!(t[1].0 - t[0].0, 5.0);
        assert!(ticks(1.0, 1.0).is_empty());
        assert_eq!(tick_label(0.30000000000000004, true, false), "0.3");
        assert_eq!(tick_label(1500.0, true, false), "1500");
        assert_eq!(tick_label(2.0, true, true), "100");
        assert_eq!(tick_label(-0.0125, true, false), "-0.0125");
    }

    #[test]
    fn series_land_where_the_data_says() {
        // A horizontal red line at y = 1 across x in [0, 10], and a blue point at (10, 0).
        let plot = Plot::new("t", "x", "y")
            .with_series("line", vec![(0.0, 1.0), (10.0, 1.0)], Style::Line)
            .with_series("pt", vec![(10.0, 0.0)], Style::Points);
        let img = plot.render().unwrap();
        assert_eq!(img.dimensions(), (640, 400));
        let f = Frame {
            left: MARGIN_LEFT as f64,
            right: (640 - MARGIN_RIGHT) as f64,
            top: MARGIN_TOP as f64,
            bottom: (400 - MARGIN_BOTTOM) as f64,
            x0: -0.5,
            x1: 10.5,
            y0: -0.05,
            y1: 1.05,
        };
        let (lx, ly) = f.to_pixel(2.0, 1.0);
        assert_eq!(
            *img.get_pixel(lx.round() as u32, ly.round() as u32),
            Rgb(PALETTE[0])
        );
        let (px, py) = f.to_pixel(10.0, 0.0);
        assert_eq!(
            *img.get_pixel(px.round() as u32, py.round() as u32),
            Rgb(PALETTE[1])
        );
        let png = plot.png_bytes().unwrap();
        assert_eq!(&png[1..4], b"PNG");
    }

    #[test]
    fn empty_or_invalid_data_is_an_error() {
        let empty = Plot::new("e", "x", "y").with_series("s", vec![(f64::NAN, 1.0)], Style::Line);
        assert!(matches!(empty.render(), Err(PlotError::NoData(_))));
        let mut log = Plot::new("l", "x", "y").with_series("s", vec![(0.0, 1.0)], Style::Line);
        log.log_x = true;
        assert!(matches!(
            log.render(),
            Err(PlotError::NonPositiveOnLogAxis(_))
        ));
    }
}
