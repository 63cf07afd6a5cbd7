//! Linear float images on disk (OpenEXR) and 8-bit previews (PNG). Every stage writes its
//! artefacts through here so the encodings agree.
//!
//! EXRs are written uncompressed by [`write_exr_rgb`] and [`write_exr_gray`]: the pipeline's
//! artefacts are its working copies and cache (DESIGN section 8 allows raw storage for those),
//! and their float samples are mostly noise that run-length coding barely shrinks (a full-size
//! separated image: 16.4 MB coded against 17.0 MB raw) while coding and decoding them cost
//! seconds of CPU per run. The `_compact` writers keep run-length coding for files that are
//! mostly one value and kept for long (a simulated capture's truth: its background is zeros).
//! Any EXR reader reads both; the readers here read either.

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

/// How an EXR's samples are stored (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ExrStorage {
    /// Scan lines, no compression: working copies.
    Raw,
    /// Run-length coded 64x64 tiles: files mostly of one value, kept for long.
    Compact,
}

impl ExrStorage {
    fn encoding(self) -> exr::prelude::Encoding {
        use exr::prelude::{Encoding, LineOrder};
        match self {
            Self::Raw => Encoding::UNCOMPRESSED,
            // Tiles in increasing order, not `FAST_LOSSLESS`'s unspecified one: the `exr` crate
            // codes tiles in parallel and, with the order unspecified, writes each where it
            // finishes, so the same image gave different bytes from run to run.
            Self::Compact => Encoding {
                line_order: LineOrder::Increasing,
                ..Encoding::FAST_LOSSLESS
            },
        }
    }
}

/// Writes linear RGB as an uncompressed 32-bit float EXR (a working copy).
pub fn write_exr_rgb(path: &Path, img: &Rgb32FImage) -> Result<(), ImageIoError> {
    write_rgb(path, img, ExrStorage::Raw)
}

/// Writes linear RGB as a run-length coded 32-bit float EXR (mostly one value, kept for long).
pub fn write_exr_rgb_compact(path: &Path, img: &Rgb32FImage) -> Result<(), ImageIoError> {
    write_rgb(path, img, ExrStorage::Compact)
}

fn write_rgb(path: &Path, img: &Rgb32FImage, storage: ExrStorage) -> Result<(), ImageIoError> {
    match (storage, RawExrRgb::new(img)) {
        (ExrStorage::Raw, Some(raw)) => {
            let written = |temporary: &Path| raw.write(temporary).map_err(exr_io_error(path));
            write_via_temporary(path, written, exr_io_error(path))
        }
        _ => write_rgb_through_exr(path, img, storage),
    }
}

/// An uncompressed scan-line RGB EXR written straight from the image's rows: the bytes the
/// `exr` crate writes (the same header attributes in the same order, one scan line per block,
/// channels in name order B, G, R, 32-bit floats). Why: through `exr` every sample went through
/// a per-pixel closure and its block buffers were copied again on their way to the file (the
/// 16 working copies of the full-size separate stage: 0.49 CPU-s, perf, of which about 0.15
/// the extraction and 0.12 the copies).
struct RawExrRgb<'a> {
    img: &'a Rgb32FImage,
    width: usize,
    /// Bytes of one block's samples (`width` x 3 x 4).
    row_bytes: i32,
}

impl<'a> RawExrRgb<'a> {
    /// `None` for the images `exr` itself should write (empty, or a block size beyond `i32`).
    fn new(img: &'a Rgb32FImage) -> Option<Self> {
        let width = img.width() as usize;
        let row_bytes = i32::try_from(width.checked_mul(12)?).ok()?;
        let fits = i32::try_from(img.height()).is_ok() && width > 0 && img.height() > 0;
        (fits && img.as_raw().len() == width * img.height() as usize * 3).then_some(Self {
            img,
            width,
            row_bytes,
        })
    }

    /// The header: magic, version 2 (single-part scan lines), the attributes, their end.
    fn header(&self) -> Vec<u8> {
        let height = self.img.height() as i32;
        let mut out = vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0];
        let mut attribute = |name: &str, kind: &str, value: &[u8]| {
            for text in [name, kind] {
                out.extend_from_slice(text.as_bytes());
                out.push(0);
            }
            out.extend_from_slice(&(value.len() as i32).to_le_bytes());
            out.extend_from_slice(value);
        };
        attribute("chunkCount", "int", &height.to_le_bytes());
        let mut channels = Vec::new();
        for name in [b'B', b'G', b'R'] {
            channels.extend_from_slice(&[name, 0]);
            // Pixel type 2 (32-bit float), linear flag and three reserved bytes, x and y
            // sampling 1.
            for field in [2i32, 0, 1, 1] {
                channels.extend_from_slice(&field.to_le_bytes());
            }
        }
        channels.push(0);
        attribute("channels", "chlist", &channels);
        attribute("compression", "compression", &[0]);
        attribute("lineOrder", "lineOrder", &[0]);
        let mut window = Vec::new();
        for v in [0, 0, self.width as i32 - 1, height - 1] {
            window.extend_from_slice(&v.to_le_bytes());
        }
        attribute("displayWindow", "box2i", &window);
        attribute("pixelAspectRatio", "float", &1f32.to_le_bytes());
        attribute("screenWindowCenter", "v2f", &[0; 8]);
        attribute("screenWindowWidth", "float", &1f32.to_le_bytes());
        attribute("dataWindow", "box2i", &window);
        attribute("type", "string", b"scanlineimage");
        out.push(0);
        out
    }

    /// Writes the file at `path`: header, the blocks' offsets, then each row as a block (its
    /// `y`, its size, its B, G and R samples), one `write` per row.
    fn write(&self, path: &Path) -> std::io::Result<()> {
        use std::io::Write;
        let mut file = std::fs::File::create(path)?;
        let header = self.header();
        let block = 8 + self.row_bytes as u64;
        let first = header.len() as u64 + 8 * u64::from(self.img.height());
        let mut head = header;
        for y in 0..u64::from(self.img.height()) {
            head.extend_from_slice(&(first + y * block).to_le_bytes());
        }
        file.write_all(&head)?;
        let mut row = vec![0u8; block as usize];
        for (y, pixels) in self
            .img
            .as_raw()
            .as_chunks::<3>()
            .0
            .chunks_exact(self.width)
            .enumerate()
        {
            let (tag, samples) = row.split_at_mut(8);
            tag[..4].copy_from_slice(&(y as i32).to_le_bytes());
            tag[4..].copy_from_slice(&self.row_bytes.to_le_bytes());
            let (blue, rest) = samples.as_chunks_mut::<4>().0.split_at_mut(self.width);
            let (green, red) = rest.split_at_mut(self.width);
            for (((p, b), g), r) in pixels.iter().zip(blue).zip(green).zip(red) {
                *b = p[2].to_le_bytes();
                *g = p[1].to_le_bytes();
                *r = p[0].to_le_bytes();
            }
            file.write_all(&row)?;
        }
        Ok(())
    }
}

/// Writes an RGB EXR through the `exr` crate.
fn write_rgb_through_exr(
    path: &Path,
    img: &Rgb32FImage,
    storage: ExrStorage,
) -> Result<(), ImageIoError> {
    use exr::prelude::*;
    let size = (img.width() as usize, img.height() as usize);
    let channels = SpecificChannels::rgb(|Vec2(x, y): Vec2<usize>| {
        let p = img.get_pixel(x as u32, y as u32).0;
        (p[0], p[1], p[2])
    });
    let image = Image::from_encoded_channels(size, storage.encoding(), channels);
    write_via_temporary(
        path,
        |temporary| {
            image
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

/// An I/O error (flush, rename) of writing EXR `path`.
fn exr_io_error(path: &Path) -> impl FnOnce(std::io::Error) -> ImageIoError + '_ {
    move |e| ImageIoError::Exr {
        path: path.to_owned(),
        source: exr::error::Error::Io(e),
    }
}

/// Reads the RGB channels of an EXR (alpha ignored, missing channels read as 0) as an image:
/// [`read_exr_rgb_pixels`]' pixels, not copied.
pub fn read_exr_rgb(path: &Path) -> Result<Rgb32FImage, ImageIoError> {
    let (width, height, pixels) = read_exr_rgb_pixels(path)?;
    // Always `width * height` pixels: `read_exr_rgb_pixels` allocates exactly that many.
    Rgb32FImage::from_raw(width, height, pixels.into_flattened()).ok_or_else(|| ImageIoError::Exr {
        path: path.to_owned(),
        source: exr::error::Error::Invalid("pixel count differs from the resolution".into()),
    })
}

/// The RGB channels of an EXR (alpha ignored, missing channels read as 0) as its width, height
/// and row-major pixels, read straight into them. Why: the per-pixel stages index pixels as
/// `[f32; 3]`, and copying them out of an image (a second frame-sized buffer to
/// fault in) was 8 % of the full-size profiles stage's CPU time (perf).
pub fn read_exr_rgb_pixels(path: &Path) -> Result<(u32, u32, Vec<[f32; 3]>), ImageIoError> {
    use exr::prelude::*;
    let image = read_first_rgba_layer_from_file(
        path,
        |resolution, _| {
            let (w, h) = (resolution.width(), resolution.height());
            (w, h, vec![[0.0f32; 3]; w * h])
        },
        |(w, _, pixels): &mut (usize, usize, Vec<[f32; 3]>),
         pos,
         (r, g, b, _a): (f32, f32, f32, f32)| {
            if let Some(p) = pixels.get_mut(pos.y() * *w + pos.x()) {
                *p = [r, g, b];
            }
        },
    )
    .map_err(|source| ImageIoError::Exr {
        path: path.to_owned(),
        source,
    })?;
    let (w, h, pixels) = image.layer_data.channel_data.pixels;
    Ok((w as u32, h as u32, pixels))
}

/// Writes a single-channel float image as an uncompressed EXR with one channel named `Y` (a
/// working copy).
pub fn write_exr_gray(path: &Path, img: &GrayF32) -> Result<(), ImageIoError> {
    write_gray(path, img, ExrStorage::Raw)
}

/// Writes a single-channel float image as a run-length coded EXR with one channel named `Y`
/// (mostly one value, kept for long).
pub fn write_exr_gray_compact(path: &Path, img: &GrayF32) -> Result<(), ImageIoError> {
    write_gray(path, img, ExrStorage::Compact)
}

fn write_gray(path: &Path, img: &GrayF32, storage: ExrStorage) -> Result<(), ImageIoError> {
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
        storage.encoding(),
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
        image::Rgb(p.map(|v| srgb_byte(v * scale)))
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

/// The 8-bit sRGB code of linear `v`: `(linear_to_srgb(v) * 255).round()`, the same byte, read
/// from a table instead of a `powf` per sample. Why: the separate stage's preview converts 17
/// million samples at full size, and `powf` with the rounding was most of its 0.26 CPU-s.
pub fn srgb_byte(v: f32) -> u8 {
    SrgbBytes::get().byte(v)
}

/// [`srgb_byte`]'s table: for every bucket of floats sharing their top 16 bits in [0, 1), the
/// byte at the bucket's first float and the first float of the bucket with the next byte.
/// Within a bucket the byte rises by at most 1: the curve's steepest slope, 12.92 x 255 per
/// unit, over the widest bucket below 1 (2^-8) that would be 12.9, but where the slope is that
/// steep (v < 0.004) a bucket is at most 2^-16 wide, and near 1 (slope 112) 2^-8 wide: 0.05
/// and 0.44 codes (the test checks every bucket's last float).
struct SrgbBytes {
    /// Per bucket: (byte at its first float, first float bits with byte + 1, or `u32::MAX`).
    buckets: Vec<(u8, u32)>,
}

/// Bits below the bucket index in an `f32`.
const SRGB_BUCKET_SHIFT: u32 = 16;

impl SrgbBytes {
    fn get() -> &'static Self {
        static TABLE: std::sync::OnceLock<SrgbBytes> = std::sync::OnceLock::new();
        TABLE.get_or_init(Self::new)
    }

    /// The exact rule, sample by sample.
    fn exact(v: f32) -> u8 {
        (linear_to_srgb(v) * 255.0).round() as u8
    }

    fn new() -> Self {
        let buckets = (0..1.0f32.to_bits() >> SRGB_BUCKET_SHIFT)
            .map(|b| {
                let first = b << SRGB_BUCKET_SHIFT;
                let last = first | ((1 << SRGB_BUCKET_SHIFT) - 1);
                let byte = Self::exact(f32::from_bits(first));
                if Self::exact(f32::from_bits(last)) == byte {
                    return (byte, u32::MAX);
                }
                // The first float with the next byte (the rule rises with v).
                let (mut lo, mut hi) = (first, last);
                while lo + 1 < hi {
                    let mid = lo + (hi - lo) / 2;
                    if Self::exact(f32::from_bits(mid)) > byte {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                (byte, hi)
            })
            .collect();
        Self { buckets }
    }

    fn byte(&self, v: f32) -> u8 {
        // NaN, negatives and zero give 0; 1 and above 255, as the clamp in `linear_to_srgb`.
        if v.is_nan() || v <= 0.0 {
            return 0;
        }
        let bits = v.to_bits();
        match self.buckets.get((bits >> SRGB_BUCKET_SHIFT) as usize) {
            Some(&(byte, next)) => byte + u8::from(bits >= next),
            None => 255,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The table's byte is the rule's at every code's edge (the floats either side of each
    /// bucket's step and each bucket's ends), at special values and at a million random floats
    /// in and around [0, 1]. (Run once over every float in [0, 1]: equal for all 1 065 353 217.)
    #[test]
    fn srgb_byte_equals_the_rounded_transfer_function() {
        let table = SrgbBytes::get();
        let check = |v: f32| assert_eq!(srgb_byte(v), SrgbBytes::exact(v), "v = {v:e}");
        for &(_, next) in &table.buckets {
            if next != u32::MAX {
                (next - 2..=next + 2).for_each(|b| check(f32::from_bits(b)));
            }
        }
        for b in 0..table.buckets.len() as u32 {
            let first = b << SRGB_BUCKET_SHIFT;
            check(f32::from_bits(first));
            check(f32::from_bits(first + (1 << SRGB_BUCKET_SHIFT) - 1));
        }
        for v in [
            f32::NAN,
            f32::NEG_INFINITY,
            -1.0,
            -0.0,
            0.0,
            f32::MIN_POSITIVE,
            0.003_130_8,
            0.5,
            1.0,
            1.0 + f32::EPSILON,
            2.0,
            f32::INFINITY,
        ] {
            check(v);
        }
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..1_000_000 {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            check(f32::from_bits((state >> 32) as u32 % 0x3fa0_0000));
        }
    }

    /// Samples of every kind a stage writes: signs, tiny and huge magnitudes, runs of one value.
    fn awkward_sample(i: usize) -> f32 {
        match i % 7 {
            0 => 0.0,
            1 => -1e-3 * i as f32,
            2 => f32::MIN_POSITIVE / 3.0,
            3 => 1e30,
            4 => f32::INFINITY,
            _ => (i as f32).sqrt(),
        }
    }

    #[test]
    fn exr_round_trips_rgb_and_gray_bit_for_bit_in_both_storages() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (37, 21);
        let rgb = Rgb32FImage::from_fn(w, h, |x, y| {
            let i = (y * w + x) as usize;
            image::Rgb([
                awkward_sample(i),
                awkward_sample(i + 1),
                awkward_sample(3 * i),
            ])
        });
        let mut gray = GrayF32::new(w, h);
        for (i, v) in gray.data.iter_mut().enumerate() {
            *v = awkward_sample(5 * i);
        }
        gray.data[7] = f32::NAN;
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let writers: [(&str, WriteRgb, WriteGray); 2] = [
            ("raw", write_exr_rgb, write_exr_gray),
            ("compact", write_exr_rgb_compact, write_exr_gray_compact),
        ];
        for (name, write_rgb, write_gray) in writers {
            let p = dir.path().join(format!("{name}_rgb.exr"));
            write_rgb(&p, &rgb).unwrap();
            assert_eq!(
                bits(read_exr_rgb(&p).unwrap().as_raw()),
                bits(rgb.as_raw()),
                "{name}"
            );
            let (pw, ph, pixels) = read_exr_rgb_pixels(&p).unwrap();
            assert_eq!((pw, ph), (w, h), "{name}");
            assert_eq!(bits(pixels.as_flattened()), bits(rgb.as_raw()), "{name}");
            let g = dir.path().join(format!("{name}_gray.exr"));
            write_gray(&g, &gray).unwrap();
            let back = read_exr_gray(&g).unwrap();
            assert_eq!((back.width, back.height), (w, h), "{name}");
            assert_eq!(bits(&back.data), bits(&gray.data), "{name}");
        }
    }

    /// The working copies' EXR writer writes the bytes the `exr` crate writes, at shapes from
    /// one pixel to long rows and tall columns, samples of every kind (NaN included).
    #[test]
    fn raw_rgb_exr_is_the_exr_crates_file_byte_for_byte() {
        let dir = tempfile::tempdir().unwrap();
        for (w, h) in [(1, 1), (37, 21), (3, 200), (1379, 4), (64, 64)] {
            let rgb = Rgb32FImage::from_fn(w, h, |x, y| {
                let i = (y * w + x) as usize;
                image::Rgb([
                    awkward_sample(i),
                    awkward_sample(2 * i + 1),
                    if i % 11 == 5 {
                        f32::NAN
                    } else {
                        -awkward_sample(i + 3)
                    },
                ])
            });
            let ours = dir.path().join("ours.exr");
            let theirs = dir.path().join("theirs.exr");
            write_exr_rgb(&ours, &rgb).unwrap();
            write_rgb_through_exr(&theirs, &rgb, ExrStorage::Raw).unwrap();
            let (a, b) = (
                std::fs::read(&ours).unwrap(),
                std::fs::read(&theirs).unwrap(),
            );
            assert_eq!(a.len(), b.len(), "{w}x{h}");
            assert!(a == b, "{w}x{h}: first difference at byte {:?}", {
                a.iter().zip(&b).position(|(x, y)| x != y)
            });
        }
    }

    type WriteRgb = fn(&Path, &Rgb32FImage) -> Result<(), ImageIoError>;
    type WriteGray = fn(&Path, &GrayF32) -> Result<(), ImageIoError>;
    /// A writer of one test image to the path it is given.
    type Write<'a> = &'a dyn Fn(&Path) -> Result<(), ImageIoError>;

    /// The compression recorded in the first header of the EXR at `path`.
    fn compression_of(path: &Path) -> exr::compression::Compression {
        let meta = exr::meta::MetaData::read_from_file(path, false).unwrap();
        meta.headers[0].compression
    }

    /// Regression test: compact EXRs (a simulated capture's truth) were written with their tiles
    /// in the order the parallel coder finished them, so the same image gave different bytes.
    /// The tiles are now in increasing order and repeated writes give the same file.
    #[test]
    fn compact_exrs_are_the_same_bytes_every_time() {
        use exr::prelude::LineOrder;
        let dir = tempfile::tempdir().unwrap();
        // 24 x 12 tiles of 64 x 64, runs of zeros and noise, as the truth images have.
        let rgb = Rgb32FImage::from_fn(1536, 768, |x, y| {
            let i = (y * 1536 + x) as usize;
            let v = if (x / 100 + y / 70) % 3 == 0 {
                0.0
            } else {
                awkward_sample(i)
            };
            image::Rgb([v, 0.5 * v, v * v])
        });
        let gray = GrayF32 {
            width: 1536,
            height: 768,
            data: rgb.pixels().map(|p| p.0[1]).collect(),
        };
        let cases: [(&str, Write); 2] = [
            ("rgb", &|p| write_exr_rgb_compact(p, &rgb)),
            ("gray", &|p| write_exr_gray_compact(p, &gray)),
        ];
        for (name, write) in cases {
            let first = dir.path().join(format!("{name}-0.exr"));
            write(&first).unwrap();
            let meta = exr::meta::MetaData::read_from_file(&first, false).unwrap();
            assert_eq!(meta.headers[0].line_order, LineOrder::Increasing, "{name}");
            let bytes = std::fs::read(&first).unwrap();
            for k in 1..4 {
                let again = dir.path().join(format!("{name}-{k}.exr"));
                write(&again).unwrap();
                assert!(
                    std::fs::read(&again).unwrap() == bytes,
                    "{name}: write {k} differs"
                );
            }
        }
    }

    #[test]
    fn working_copies_are_uncompressed_and_compact_files_run_length_coded() {
        use exr::compression::Compression;
        let dir = tempfile::tempdir().unwrap();
        let rgb = Rgb32FImage::from_fn(9, 5, |x, y| image::Rgb([x as f32, y as f32, 0.5]));
        let gray = GrayF32::new(9, 5);
        let cases: [(&str, Write, Compression); 4] = [
            (
                "rgb_raw",
                &|p| write_exr_rgb(p, &rgb),
                Compression::Uncompressed,
            ),
            (
                "gray_raw",
                &|p| write_exr_gray(p, &gray),
                Compression::Uncompressed,
            ),
            (
                "rgb_compact",
                &|p| write_exr_rgb_compact(p, &rgb),
                Compression::RLE,
            ),
            (
                "gray_compact",
                &|p| write_exr_gray_compact(p, &gray),
                Compression::RLE,
            ),
        ];
        for (name, write, expected) in cases {
            let p = dir.path().join(format!("{name}.exr"));
            write(&p).unwrap();
            assert_eq!(compression_of(&p), expected, "{name}");
        }
    }
}
