//! A self-contained HTML report: headings, paragraphs, tables and figures whose PNG images are
//! embedded as base64 data URIs (one file to send around).

use std::io::Cursor;
use std::path::{Path, PathBuf};

use base64::Engine;
use image::{ImageFormat, RgbImage};

use mlsss_core::imageio::srgb_byte;

/// Errors of report generation.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum HtmlReportError {
    /// An image could not be encoded as PNG.
    #[error("encoding image `{label}` as PNG: {source}")]
    Png {
        label: String,
        source: image::ImageError,
    },
    /// The image buffer does not match its size.
    #[error("image `{label}`: {pixels} pixels for {width}x{height}")]
    ImageSize {
        label: String,
        pixels: usize,
        width: u32,
        height: u32,
    },
    /// The report could not be written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// One image of a figure: PNG or SVG bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    pub label: String,
    pub bytes: Vec<u8>,
    /// `image/png` or `image/svg+xml`.
    pub mime: &'static str,
}

impl Panel {
    pub fn png(label: &str, bytes: Vec<u8>) -> Self {
        Self {
            label: label.to_owned(),
            bytes,
            mime: "image/png",
        }
    }

    /// A panel from an image file beside the report (PNG or SVG by extension); `None` when the
    /// file cannot be read (figures of optional stages).
    pub fn from_file(label: &str, path: &Path) -> Option<Self> {
        let bytes = std::fs::read(path).ok()?;
        let mime = match path.extension().and_then(|e| e.to_str()) {
            Some("svg") => "image/svg+xml",
            Some("png") => "image/png",
            _ => return None,
        };
        Some(Self {
            label: label.to_owned(),
            bytes,
            mime,
        })
    }
}

#[derive(Debug, Clone, PartialEq)]
enum Block {
    Heading(String),
    Paragraph(String),
    Table {
        header: Vec<String>,
        rows: Vec<Vec<String>>,
    },
    Figure {
        caption: String,
        panels: Vec<Panel>,
    },
    Preformatted(String),
}

/// The report being built.
#[derive(Debug, Clone, PartialEq)]
pub struct HtmlReport {
    title: String,
    blocks: Vec<Block>,
}

/// `<`, `>`, `&` and quotes escaped for HTML text and attributes.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '&' => out.push_str("&amp;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// PNG bytes of an 8-bit RGB image.
pub fn png_bytes(img: &RgbImage, label: &str) -> Result<Vec<u8>, HtmlReportError> {
    let mut bytes = Vec::new();
    img.write_to(&mut Cursor::new(&mut bytes), ImageFormat::Png)
        .map_err(|source| HtmlReportError::Png {
            label: label.to_owned(),
            source,
        })?;
    Ok(bytes)
}

/// An sRGB preview of a linear RGB image: `white` maps to full scale, values clipped.
pub fn linear_preview(
    pixels: &[[f32; 3]],
    width: u32,
    height: u32,
    white: f32,
    label: &str,
) -> Result<RgbImage, HtmlReportError> {
    if pixels.len() != (width as usize) * (height as usize) {
        return Err(HtmlReportError::ImageSize {
            label: label.to_owned(),
            pixels: pixels.len(),
            width,
            height,
        });
    }
    let scale = if white > 0.0 { 1.0 / white } else { 1.0 };
    Ok(RgbImage::from_fn(width, height, |x, y| {
        let p = pixels[(y * width + x) as usize];
        image::Rgb(p.map(|v| {
            let v = if v.is_finite() { v * scale } else { 0.0 };
            srgb_byte(v.clamp(0.0, 1.0))
        }))
    }))
}

impl HtmlReport {
    pub fn new(title: &str) -> Self {
        Self {
            title: title.to_owned(),
            blocks: Vec::new(),
        }
    }

    pub fn heading(&mut self, text: &str) -> &mut Self {
        self.blocks.push(Block::Heading(text.to_owned()));
        self
    }

    pub fn paragraph(&mut self, text: &str) -> &mut Self {
        self.blocks.push(Block::Paragraph(text.to_owned()));
        self
    }

    pub fn preformatted(&mut self, text: &str) -> &mut Self {
        self.blocks.push(Block::Preformatted(text.to_owned()));
        self
    }

    pub fn table(&mut self, header: &[&str], rows: Vec<Vec<String>>) -> &mut Self {
        self.blocks.push(Block::Table {
            header: header.iter().map(|s| (*s).to_owned()).collect(),
            rows,
        });
        self
    }

    pub fn figure(&mut self, caption: &str, panels: Vec<Panel>) -> &mut Self {
        self.blocks.push(Block::Figure {
            caption: caption.to_owned(),
            panels,
        });
        self
    }

    /// The whole document.
    pub fn to_html(&self) -> String {
        let b64 = base64::engine::general_purpose::STANDARD;
        let mut html = format!(
            "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
             <title>{t}</title><style>\
             body{{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}}\
             table{{border-collapse:collapse;margin:1em 0}}\
             td,th{{border:1px solid #bbb;padding:3px 8px;text-align:right}}\
             th{{background:#eee}} td:first-child{{text-align:left}}\
             figure{{margin:1.5em 0}} .panels{{display:flex;flex-wrap:wrap;gap:10px}}\
             .panel{{text-align:center;font-size:90%}} .panel img{{display:block;image-rendering:pixelated}}\
             pre{{background:#f6f6f6;padding:8px;overflow:auto}}\
             </style></head><body>\n<h1>{t}</h1>\n",
            t = escape(&self.title)
        );
        for block in &self.blocks {
            match block {
                Block::Heading(t) => html.push_str(&format!("<h2>{}</h2>\n", escape(t))),
                Block::Paragraph(t) => html.push_str(&format!("<p>{}</p>\n", escape(t))),
                Block::Preformatted(t) => html.push_str(&format!("<pre>{}</pre>\n", escape(t))),
                Block::Table { header, rows } => {
                    html.push_str("<table><tr>");
                    for h in header {
                        html.push_str(&format!("<th>{}</th>", escape(h)));
                    }
                    html.push_str("</tr>\n");
                    for row in rows {
                        html.push_str("<tr>");
                        for cell in row {
                            html.push_str(&format!("<td>{}</td>", escape(cell)));
                        }
                        html.push_str("</tr>\n");
                    }
                    html.push_str("</table>\n");
                }
                Block::Figure { caption, panels } => {
                    html.push_str("<figure><div class=\"panels\">");
                    for p in panels {
                        html.push_str(&format!(
                            "<div class=\"panel\"><img alt=\"{l}\" src=\"data:{m};base64,{d}\">{l}</div>",
                            l = escape(&p.label),
                            m = p.mime,
                            d = b64.encode(&p.bytes)
                        ));
                    }
                    html.push_str(&format!(
                        "</div><figcaption>{}</figcaption></figure>\n",
                        escape(caption)
                    ));
                }
            }
        }
        html.push_str("</body></html>\n");
        html
    }

    /// Writes the document to `path`.
    pub fn save(&self, path: &Path) -> Result<(), HtmlReportError> {
        mlsss_core::atomic_file::write_bytes_atomically(path, self.to_html()).map_err(|source| {
            HtmlReportError::Io {
                path: path.to_owned(),
                source,
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_document_embeds_images_and_escapes_text() {
        let img = linear_preview(&[[1.0, 0.0, 0.0], [0.18, 0.18, 0.18]], 2, 1, 1.0, "x").unwrap();
        assert_eq!(img.get_pixel(0, 0).0, [255, 0, 0]);
        // 18 % grey is sRGB 118.
        assert_eq!(img.get_pixel(1, 0).0[0], 118);
        let png = png_bytes(&img, "x").unwrap();
        let mut r = HtmlReport::new("A <test> & more");
        r.heading("Metrics")
            .table(&["name", "value"], vec![vec!["psnr".into(), "31.2".into()]])
            .figure("two pixels", vec![Panel::png("real", png.clone())])
            .paragraph("x < y");
        let html = r.to_html();
        assert!(html.starts_with("<!DOCTYPE html>"));
        assert!(html.contains("<h1>A &lt;test&gt; &amp; more</h1>"));
        assert!(html.contains("<td>psnr</td><td>31.2</td>"));
        assert!(html.contains("x &lt; y"));
        let encoded = base64::engine::general_purpose::STANDARD.encode(&png);
        assert!(html.contains(&format!("data:image/png;base64,{encoded}")));
        assert!(html.trim_end().ends_with("</html>"));
        assert!(matches!(
            linear_preview(&[[0.0; 3]], 2, 2, 1.0, "bad"),
            Err(HtmlReportError::ImageSize { .. })
        ));
    }
}
