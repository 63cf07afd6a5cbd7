//! Linear float images on disk (OpenEXR) and 8-bit previews (PNG). Every stage writes its
//! artefacts through here so the encodings agree.

use std::path::{Path, PathBuf};

use image::Rgb32FImage;

use crate::atomic_file::write_via_temporary;

/// Errors reading or writing images.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ImageIoError {
    /// The EXR file could not be read or written.
    #[error("{path}: {source}")]
    Exr {
        path: PathBuf,
        source: exr::error::Error,
    },
    /// The PNG file could not be read or written.
    #[error("{path}: {source}")]
    Png {
        path: PathBuf,
        source: image::ImageError,
    },
    /// Buffer and stated size disagree.
    #[error("{path}: image buffer does not match its size {width}x{height}")]
    Size {
        path: PathBuf,
        width: u32,
        height: u32,
    },
}

/// A single-channel float image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct GrayF32 {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

impl GrayF32 {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0.0; width as usize * height as usize],
        }
    }

    pub fn get(&self, x: u32, y: u32) -> f32 {
        self.data[y as usize * self.width as usize + x as usize]
    }

    pub fn set(&mut self, x: u32, y: u32, v: f32) {
        self.data[y as usize * self.width as usize + x as usize] = v;
    }
}

/// Writes linear RGB as a 32-bit float EXR.
pub fn write_exr_rgb(path: &Path, img: &Rgb32FImage) -> Result<(), ImageIoError> {
    write_via_temporary(
        path,
        |temporary| {
            exr::prelude::write_rgb_file(
                temporary,
                img.width() as usize,
                img.height() as usize,
                |x, y| {
                    let p = img.get_pixel(x as u32, y as u32).0;
                    (p[0], p[1], p[2])
                },
            )
            .map_err(|source| ImageIoError::Exr {
                path: path.to_owned(),
                source,
            })
        },
        exr_io_error(path),
    )
}

/// An I/O error (flush, rename) of writing EXR `path`.
fn exr_io_error(path: &Path) -> impl FnOnce(std::io::Error) -> ImageIoError + '_ {
    move |e| ImageIoError::Exr {
        path: path.to_owned(),
        source: exr::error::Error::Io(e),
    }
}

/// Reads the RGB channels of an EXR (alpha ignored, missing channels read as 0).
pub fn read_exr_rgb(path: &Path) -> Result<Rgb32FImage, ImageIoError> {
    use exr::prelude::*;
    let image = read_first_rgba_layer_from_file(
        path,
        |resolution, _| Rgb32FImage::new(resolution.width() as u32, resolution.height() as u32),
        |img: &mut Rgb32FImage, pos, (r, g, b, _a): (f32, f32, f32, f32)| {
            img.put_pixel(pos.x() as u32, pos.y() as u32, image::Rgb([r, g, b]))
        },
    )
    .map_err(|source| ImageIoError::Exr {
        path: path.to_owned(),
        source,
    })?;
    Ok(image.layer_data.channel_data.pixels)
}

/// Writes a single-channel float image as an EXR with one channel named `Y`.
pub fn write_exr_gray(path: &Path, img: &GrayF32) -> Result<(), ImageIoError> {
    use exr::prelude::*;
    if img.data.len() != img.width as usize * img.height as usize {
        return Err(ImageIoError::Size {
            path: path.to_owned(),
            width: img.width,
            height: img.height,
        });
    }
    let size = (img.width as usize, img.height as usize);
    let channel = AnyChannel::new("Y", FlatSamples::F32(img.data.clone()));
    let layer = Layer::new(
        size,
        LayerAttributes::default(),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(smallvec::smallvec![channel]),
    );
    write_via_temporary(
        path,
        |temporary| {
            Image::from_layer(layer)
                .write()
                .to_file(temporary)
                .map_err(|source| ImageIoError::Exr {
                    path: path.to_owned(),
                    source,
                })
        },
        exr_io_error(path),
    )
}

/// Reads the first channel of the first layer of an EXR as a single-channel float image.
pub fn read_exr_gray(path: &Path) -> Result<GrayF32, ImageIoError> {
    use exr::prelude::*;
    let image = read_first_flat_layer_from_file(path).map_err(|source| ImageIoError::Exr {
        path: path.to_owned(),
        source,
    })?;
    let size = image.layer_data.size;
    let data: Vec<f32> = image.layer_data.channel_data.list[0]
        .sample_data
        .values_as_f32()
        .collect();
    Ok(GrayF32 {
        width: size.0 as u32,
        height: size.1 as u32,
        data,
    })
}

/// Writes linear RGB as an 8-bit sRGB PNG preview, scaled so that `white` maps to 1.
pub fn write_png_preview(path: &Path, img: &Rgb32FImage, white: f32) -> Result<(), ImageIoError> {
    let scale = if white > 0.0 { 1.0 / white } else { 1.0 };
    let out = image::RgbImage::from_fn(img.width(), img.height(), |x, y| {
        let p = img.get_pixel(x, y).0;
        image::Rgb(p.map(|v| (linear_to_srgb(v * scale) * 255.0).round() as u8))
    });
    write_png(path, &out)
}

/// Writes a PNG (previews, figures; grey or RGB) whole or not at all.
pub fn write_png<P>(
    path: &Path,
    img: &image::ImageBuffer<P, Vec<P::Subpixel>>,
) -> Result<(), ImageIoError>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
{
    write_via_temporary(
        path,
        |temporary| {
            img.save_with_format(temporary, image::ImageFormat::Png)
                .map_err(|source| ImageIoError::Png {
                    path: path.to_owned(),
                    source,
                })
        },
        |e| ImageIoError::Png {
            path: path.to_owned(),
            source: image::ImageError::IoError(e),
        },
    )
}

/// The sRGB transfer function, input clamped to [0, 1] (NaN maps to 0).
pub fn linear_to_srgb(v: f32) -> f32 {
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exr_round_trips_rgb_and_gray_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let rgb = Rgb32FImage::from_fn(7, 4, |x, y| image::Rgb([x as f32, y as f32 * 0.5, -1e-3]));
        let p = dir.path().join("a.exr");
        write_exr_rgb(&p, &rgb).unwrap();
        assert_eq!(read_exr_rgb(&p).unwrap(), rgb);

        let mut gray = GrayF32::new(5, 3);
        gray.set(4, 2, 123.25);
        gray.set(0, 1, f32::NAN);
        let g = dir.path().join("g.exr");
        write_exr_gray(&g, &gray).unwrap();
        let back = read_exr_gray(&g).unwrap();
        assert_eq!((back.width, back.height), (5, 3));
        assert_eq!(back.get(4, 2), 123.25);
        assert!(back.get(0, 1).is_nan());
    }
}
