//! Figures of the held-out relighting (paper Figs. 9-11): side-by-side images of the recorded
//! frame and the renders under one pattern, and a scanline plot of one channel.
//!
//! Conventions: images are camera-sized linear RGB, row-major (`y * width + x`); the mask marks
//! the compared pixels (others are shown black in the panels).

use super::html::{HtmlReportError, Panel, linear_preview, png_bytes};
use super::plot::{Plot, PlotError, Style};

/// One pattern of the held-out projector: what the camera recorded and each renderer's result.
#[derive(Debug, Clone, PartialEq)]
pub struct RelitImages {
    /// Pattern name (e.g. `white`, `gray-x-3`).
    pub pattern: String,
    pub width: u32,
    pub height: u32,
    /// Recorded frame minus stray light.
    pub reference: Vec<[f32; 3]>,
    /// `(renderer name, image)`.
    pub renders: Vec<(String, Vec<[f32; 3]>)>,
}

/// The value of `channel` at the given quantile (0..1) over the masked pixels (0 if none).
pub fn masked_quantile(pixels: &[[f32; 3]], mask: &[bool], channel: usize, q: f64) -> f32 {
    let mut v: Vec<f32> = pixels
        .iter()
        .zip(mask)
        .filter(|(p, m)| **m && p[channel].is_finite())
        .map(|(p, _)| p[channel])
        .collect();
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f32::total_cmp);
    let i = ((v.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
    v[i]
}

/// Panels: the reference then each render, all at the reference's exposure (its 99th percentile
/// of the brightest channel maps to white), pixels outside the mask black.
pub fn comparison_panels(
    images: &RelitImages,
    mask: &[bool],
) -> Result<Vec<Panel>, HtmlReportError> {
    let white = (0..3)
        .map(|c| masked_quantile(&images.reference, mask, c, 0.99))
        .fold(0.0f32, f32::max);
    let masked = |px: &[[f32; 3]]| -> Vec<[f32; 3]> {
        px.iter()
            .zip(mask)
            .map(|(p, &m)| if m { *p } else { [0.0; 3] })
            .collect()
    };
    let mut panels = Vec::new();
    let all = std::iter::once(("recorded".to_owned(), &images.reference))
        .chain(images.renders.iter().map(|(n, p)| (n.clone(), p)));
    for (name, px) in all {
        let label = format!("{name} ({})", images.pattern);
        let img = linear_preview(&masked(px), images.width, images.height, white, &label)?;
        panels.push(Panel::png(&label, png_bytes(&img, &label)?));
    }
    Ok(panels)
}

/// The row a quarter down the mask's extent (the forehead of a head seen upright) and the masked
/// columns' range on it; `None` for an empty mask.
pub fn forehead_row(mask: &[bool], width: usize) -> Option<(usize, usize, usize)> {
    let rows: Vec<usize> = mask
        .chunks(width)
        .enumerate()
        .filter(|(_, r)| r.iter().any(|m| *m))
        .map(|(y, _)| y)
        .collect();
    let (&top, &bottom) = (rows.first()?, rows.last()?);
    let y = top + (bottom - top) / 4;
    let row = &mask[y * width..(y + 1) * width];
    let x0 = row.iter().position(|m| *m)?;
    let x1 = row.iter().rposition(|m| *m)?;
    Some((y, x0, x1))
}

/// Paper Fig. 10 for the held-out projector: `channel` along the forehead row, recorded against
/// each render.
pub fn scanline_plot(
    images: &RelitImages,
    mask: &[bool],
    channel: usize,
) -> Result<Option<Plot>, PlotError> {
    let w = images.width as usize;
    let Some((y, x0, x1)) = forehead_row(mask, w) else {
        return Ok(None);
    };
    let names = ["R", "G", "B"];
    let series = |px: &[[f32; 3]]| -> Vec<(f64, f64)> {
        (x0..=x1)
            .filter(|&x| mask[y * w + x])
            .map(|x| (x as f64, f64::from(px[y * w + x][channel])))
            .collect()
    };
    let mut plot = Plot::new(
        &format!(
            "{} channel, row {y}, {}",
            names[channel % 3],
            images.pattern
        ),
        "camera column (px)",
        "radiance",
    )
    .with_series("recorded", series(&images.reference), Style::LineAndPoints);
    for (name, px) in &images.renders {
        plot = plot.with_series(name, series(px), Style::Line);
    }
    plot.width = 720;
    plot.y_from_zero = true;
    plot.render()?;
    Ok(Some(plot))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn images() -> (RelitImages, Vec<bool>) {
        let (w, h) = (8u32, 8u32);
        let n = (w * h) as usize;
        let reference: Vec<[f32; 3]> = (0..n).map(|i| [i as f32 / n as f32; 3]).collect();
        let render: Vec<[f32; 3]> = reference.iter().map(|p| p.map(|v| v * 0.5)).collect();
        // Mask: rows 2..=5, columns 1..=6.
        let mask = (0..n)
            .map(|i| (2..=5).contains(&(i / 8)) && (1..=6).contains(&(i % 8)))
            .collect();
        (
            RelitImages {
                pattern: "white".into(),
                width: w,
                height: h,
                reference,
                renders: vec![("mlsss".into(), render)],
            },
            mask,
        )
    }

    #[test]
    fn forehead_row_is_a_quarter_down_the_mask() {
        let (_, mask) = images();
        assert_eq!(forehead_row(&mask, 8), Some((2, 1, 6)));
        assert_eq!(forehead_row(&[false; 16], 4), None);
    }

    #[test]
    fn panels_share_the_reference_exposure_and_black_out_the_background() {
        let (img, mask) = images();
        let panels = comparison_panels(&img, &mask).unwrap();
        assert_eq!(panels.len(), 2);
        assert_eq!(panels[0].label, "recorded (white)");
        let decode = |p: &Panel| image::load_from_memory(&p.bytes).unwrap().to_rgb8();
        let (rec, ren) = (decode(&panels[0]), decode(&panels[1]));
        assert_eq!(rec.get_pixel(0, 0).0, [0, 0, 0]);
        // The brightest masked pixel of the reference is at full scale; the half-bright render
        // is darker at the same place.
        assert_eq!(rec.get_pixel(6, 5).0[0], 255);
        assert!(ren.get_pixel(6, 5).0[0] < 255);
        let q = masked_quantile(&img.reference, &mask, 0, 0.0);
        assert_eq!(q, 17.0 / 64.0);
    }

    #[test]
    fn the_scanline_plot_has_one_series_per_image() {
        let (img, mask) = images();
        let plot = scanline_plot(&img, &mask, 0).unwrap().unwrap();
        assert_eq!(plot.series.len(), 2);
        assert_eq!(plot.series[0].points.len(), 6);
        assert_eq!(
            plot.series[1].points[0],
            (1.0, f64::from(17.0f32 / 64.0 * 0.5))
        );
    }
}
