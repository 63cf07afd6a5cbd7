//! The figures' font: DejaVu Sans embedded in the binary (`fonts/DejaVuSans.ttf`, Bitstream Vera
//! licence in `fonts/LICENSE`), registered with `plotters` for text layout, and [`Raster`], the
//! bitmap backend that draws its glyphs.
//!
//! Why a backend of our own: `plotters`' `ab_glyph` text drawing places each glyph's bitmap at the
//! pen position without the glyph's side bearing, so letters sit unevenly ("th e"). [`Raster`] is
//! `plotters`' `BitMapBackend` for every shape, and draws text itself with the same advances and
//! kerning `plotters` lays text out with, each glyph at its bearing and on a common baseline.
//!
//! Conventions: backend coordinates are pixels from the top-left corner; a text's layout box is
//! `plotters`' (width = advances + kerning at a pixel scale of the font size, height = size / 1.24),
//! with the baseline at the font's ascent below its top.

use std::sync::Once;

use ab_glyph::{Font, FontRef, PxScale, ScaleFont, point};
use plotters::backend::BitMapBackend;
use plotters::style::{FontStyle, FontTransform, register_font};
use plotters_backend::text_anchor::{HPos, VPos};
use plotters_backend::{
    BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingBackend, DrawingErrorKind,
};

/// DejaVu Sans 2.37, unmodified.
pub static FONT: &[u8] = include_bytes!("fonts/DejaVuSans.ttf");
/// The family the embedded font is registered under; every text style of the figures names it.
pub const FAMILY: &str = "sans-serif";

/// Registers the embedded font with `plotters` under [`FAMILY`] (once per process).
pub fn register() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // A parse failure (impossible for the embedded bytes, which the tests parse) would show
        // as a font error when the first text is laid out.
        let _ = register_font(FAMILY, FontStyle::Normal, FONT);
    });
}

fn font() -> FontRef<'static> {
    FontRef::try_from_slice(FONT).expect("the embedded DejaVu Sans parses (tested)")
}

/// A bitmap backend drawing into an RGB buffer, with correctly spaced text.
pub struct Raster<'a> {
    inner: BitMapBackend<'a>,
    font: FontRef<'static>,
}

impl<'a> Raster<'a> {
    /// Draws into `buf`, `width * height * 3` bytes of row-major RGB.
    pub fn with_buffer(buf: &'a mut [u8], size: (u32, u32)) -> Self {
        Self {
            inner: BitMapBackend::with_buffer(buf, size),
            font: font(),
        }
    }
}

/// Width (advances plus kerning) of `text` at a pixel scale of `size`, as `plotters` lays it out.
fn advance_width(font: &FontRef<'static>, size: f32, text: &str) -> f32 {
    let scaled = font.as_scaled(PxScale::from(size));
    let mut width = 0.0;
    let mut prev = None;
    for c in text.chars() {
        let id = scaled.glyph_id(c);
        if let Some(p) = prev {
            width += scaled.kern(p, id);
        }
        width += scaled.h_advance(id);
        prev = Some(id);
    }
    width
}

impl DrawingBackend for Raster<'_> {
    type ErrorType = <BitMapBackend<'static> as DrawingBackend>::ErrorType;

    fn get_size(&self) -> (u32, u32) {
        self.inner.get_size()
    }

    fn ensure_prepared(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.ensure_prepared()
    }

    fn present(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.present()
    }

    fn draw_pixel(
        &mut self,
        point: BackendCoord,
        color: BackendColor,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_pixel(point, color)
    }

    fn draw_line<S: BackendStyle>(
        &mut self,
        from: BackendCoord,
        to: BackendCoord,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_line(from, to, style)
    }

    fn draw_rect<S: BackendStyle>(
        &mut self,
        upper_left: BackendCoord,
        bottom_right: BackendCoord,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_rect(upper_left, bottom_right, style, fill)
    }

    fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        path: I,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_path(path, style)
    }

    fn draw_circle<S: BackendStyle>(
        &mut self,
        center: BackendCoord,
        radius: u32,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_circle(center, radius, style, fill)
    }

    fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        vert: I,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.fill_polygon(vert, style)
    }

    fn blit_bitmap(
        &mut self,
        pos: BackendCoord,
        size: (u32, u32),
        src: &[u8],
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.blit_bitmap(pos, size, src)
    }

    fn estimate_text_size<S: BackendTextStyle>(
        &self,
        text: &str,
        style: &S,
    ) -> Result<(u32, u32), DrawingErrorKind<Self::ErrorType>> {
        let size = style.size() as f32;
        Ok((
            advance_width(&self.font, size, text) as u32,
            (style.size() / 1.24) as u32,
        ))
    }

    fn draw_text<S: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &S,
        pos: BackendCoord,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        let color = style.color();
        if color.alpha == 0.0 {
            return Ok(());
        }
        let size = style.size() as f32;
        let scaled = self.font.as_scaled(PxScale::from(size));
        let width = advance_width(&self.font, size, text);
        let height = size / 1.24;
        let dx = match style.anchor().h_pos {
            HPos::Left => 0.0,
            HPos::Center => -width / 2.0,
            HPos::Right => -width,
        };
        let dy = match style.anchor().v_pos {
            VPos::Top => 0.0,
            VPos::Center => -height / 2.0,
            VPos::Bottom => -height,
        };
        let transform: FontTransform = style.transform();
        let (w, h) = self.get_size();
        let mut caret = dx;
        let mut prev = None;
        for c in text.chars() {
            let id = scaled.glyph_id(c);
            if let Some(p) = prev {
                caret += scaled.kern(p, id);
            }
            prev = Some(id);
            let glyph =
                id.with_scale_and_position(scaled.scale(), point(caret, dy + scaled.ascent()));
            caret += scaled.h_advance(id);
            let Some(outline) = self.font.outline_glyph(glyph) else {
                continue; // a space
            };
            let bounds = outline.px_bounds();
            let mut ink = Vec::new();
            outline.draw(|x, y, coverage| ink.push((x, y, coverage)));
            for (x, y, coverage) in ink {
                if coverage <= 0.0 {
                    continue;
                }
                let (x, y) = transform.transform(
                    bounds.min.x as i32 + x as i32,
                    bounds.min.y as i32 + y as i32,
                );
                let (x, y) = (pos.0 + x, pos.1 + y);
                if x < 0 || y < 0 || x >= w as i32 || y >= h as i32 {
                    continue;
                }
                let alpha = color.alpha * f64::from(coverage.min(1.0));
                self.inner.draw_pixel(
                    (x, y),
                    BackendColor {
                        alpha,
                        rgb: color.rgb,
                    },
                )?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plotters::style::IntoFont;

    #[test]
    fn the_embedded_font_parses_and_registers() {
        let f = font();
        assert!(f.glyph_id('A').0 != 0 && f.glyph_id('µ').0 != 0);
        register();
        assert!(register_font("check", FontStyle::Normal, FONT).is_ok());
    }

    #[test]
    fn glyphs_keep_their_side_bearings() {
        // "ll": two identical glyphs; their ink must be exactly one advance apart.
        let (w, h) = (60u32, 30u32);
        let mut buf = vec![255u8; (w * h * 3) as usize];
        register();
        {
            let mut raster = Raster::with_buffer(&mut buf, (w, h));
            let style = plotters::style::TextStyle::from((FAMILY, 20.0).into_font());
            raster.draw_text("ll", &style, (5, 2)).unwrap();
        }
        let dark_columns: Vec<u32> = (0..w)
            .filter(|&x| (0..h).any(|y| buf[((y * w + x) * 3) as usize] < 128))
            .collect();
        assert!(dark_columns.len() >= 2, "{dark_columns:?}");
        let runs: Vec<u32> = dark_columns
            .windows(2)
            .filter(|p| p[1] != p[0] + 1)
            .map(|p| p[1])
            .collect();
        let scaled = font().into_scaled(PxScale::from(20.0));
        let advance = scaled.h_advance(scaled.glyph_id('l'));
        let gap = runs[0] - dark_columns[0];
        assert!((gap as f32 - advance).abs() <= 1.0, "{gap} vs {advance}");
        // The first l starts at its left side bearing, not at the pen position.
        let bearing = scaled.h_side_bearing(scaled.glyph_id('l'));
        assert!(
            (dark_columns[0] as f32 - 5.0 - bearing).abs() <= 1.0,
            "{dark_columns:?}"
        );
    }
}
