//! A photometric-stereo image set on disk (the DiLiGenT layout): images of one view under distant
//! lights, a light-direction file, optional per-image RGB intensities, optional mask, optional
//! ground-truth normals.
//!
//! Conventions
//! - Images are 8- or 16-bit PNG holding linear values (no sRGB decoding), read as [0, 1].
//! - Image order: `filenames.txt` in the folder if present (one name per line), else the folder's
//!   PNG files sorted by name, leaving out `mask*.png` and `normal*.png`.
//! - Text files: one row per image, numbers separated by spaces, tabs or commas; blank lines and
//!   lines starting with `#` are skipped.
//! - Ground-truth normals: EXR (RGB = n), PNG (RGB = 0.5 n + 0.5), or a level-5 `.mat` with an
//!   `H x W x 3` variable `Normal_gt`.

use std::path::{Path, PathBuf};

use image::Rgb32FImage;
use nalgebra::Vector3;

use super::mat_file;

/// Errors reading an image set.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ImageSetError {
    /// A file or folder could not be read.
    #[error("{path}: {reason}")]
    Read { path: PathBuf, reason: String },
    /// A text file has a malformed line.
    #[error("{path} line {line}: {reason}")]
    Parse {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    /// Counts or sizes disagree.
    #[error("{0}")]
    Mismatch(String),
    /// `--select` names an image that does not exist.
    #[error(
        "selected image {index} does not exist (the set has {count} images; indices start at 1)"
    )]
    BadSelection { index: usize, count: usize },
}

fn read_err(path: &Path, reason: impl ToString) -> ImageSetError {
    ImageSetError::Read {
        path: path.to_owned(),
        reason: reason.to_string(),
    }
}

/// The image files of a folder, in order.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>, ImageSetError> {
    let list = dir.join("filenames.txt");
    if list.is_file() {
        let text = std::fs::read_to_string(&list).map_err(|e| read_err(&list, e))?;
        return Ok(text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .map(|l| dir.join(l))
            .collect());
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| read_err(dir, e))?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().to_lowercase())
                .unwrap_or_default();
            name.ends_with(".png") && !name.starts_with("mask") && !name.starts_with("normal")
        })
        .collect();
    files.sort();
    Ok(files)
}

/// Rows of numbers of a text file; each row must have exactly `columns` numbers.
pub fn read_rows(path: &Path, columns: usize) -> Result<Vec<Vec<f64>>, ImageSetError> {
    let text = std::fs::read_to_string(path).map_err(|e| read_err(path, e))?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let parse_err = |reason: String| ImageSetError::Parse {
            path: path.to_owned(),
            line: i + 1,
            reason,
        };
        let values: Vec<f64> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|s| !s.is_empty())
            .map(|s| {
                s.parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| parse_err(format!("'{s}' is not a finite number")))
            })
            .collect::<Result<_, _>>()?;
        if values.len() != columns {
            return Err(parse_err(format!(
                "expected {columns} numbers, found {}",
                values.len()
            )));
        }
        rows.push(values);
    }
    Ok(rows)
}

/// Unit light directions, one `x y z` per line.
pub fn read_directions(path: &Path) -> Result<Vec<Vector3<f64>>, ImageSetError> {
    read_rows(path, 3)?
        .into_iter()
        .enumerate()
        .map(|(i, r)| {
            Vector3::new(r[0], r[1], r[2])
                .try_normalize(1e-12)
                .ok_or_else(|| ImageSetError::Parse {
                    path: path.to_owned(),
                    line: i + 1,
                    reason: "light direction is zero".into(),
                })
        })
        .collect()
}

/// Per-image RGB intensities, one `r g b` per line.
pub fn read_intensities(path: &Path) -> Result<Vec<[f64; 3]>, ImageSetError> {
    read_rows(path, 3)?
        .into_iter()
        .enumerate()
        .map(|(i, r)| {
            if r.iter().all(|&v| v >= 0.0) && r.iter().any(|&v| v > 0.0) {
                Ok([r[0], r[1], r[2]])
            } else {
                Err(ImageSetError::Parse {
                    path: path.to_owned(),
                    line: i + 1,
                    reason: "intensities must be >= 0 and not all zero".into(),
                })
            }
        })
        .collect()
}

/// An 8- or 16-bit PNG (grey or RGB, alpha ignored) as linear RGB in [0, 1].
pub fn read_linear_png(path: &Path) -> Result<Rgb32FImage, ImageSetError> {
    let img = image::open(path).map_err(|e| read_err(path, e))?;
    use image::ColorType as C;
    if !matches!(
        img.color(),
        C::L8 | C::La8 | C::Rgb8 | C::Rgba8 | C::L16 | C::La16 | C::Rgb16 | C::Rgba16
    ) {
        return Err(read_err(
            path,
            format!("unsupported pixel format {:?}", img.color()),
        ));
    }
    // to_rgb16 widens 8-bit samples by x257, so dividing by 65535 is exact for both depths.
    let rgb = img.to_rgb16();
    let (w, h) = rgb.dimensions();
    let data = rgb
        .into_raw()
        .into_iter()
        .map(|v| v as f32 / 65535.0)
        .collect();
    Rgb32FImage::from_raw(w, h, data).ok_or_else(|| read_err(path, "inconsistent image size"))
}

/// A mask PNG: non-zero pixels are in.
pub fn read_mask(path: &Path) -> Result<(u32, u32, Vec<bool>), ImageSetError> {
    let img = image::open(path)
        .map_err(|e| read_err(path, e))?
        .to_luma16();
    let (w, h) = img.dimensions();
    Ok((w, h, img.into_raw().into_iter().map(|v| v > 0).collect()))
}

/// Ground-truth normals from EXR, PNG (0.5 n + 0.5) or `.mat` (`Normal_gt`).
pub fn read_truth_normals(path: &Path) -> Result<Rgb32FImage, ImageSetError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "exr" => mlsss_core::imageio::read_exr_rgb(path).map_err(|e| read_err(path, e)),
        "png" => {
            let mut img = read_linear_png(path)?;
            for v in img.iter_mut() {
                *v = 2.0 * *v - 1.0;
            }
            Ok(img)
        }
        "mat" => {
            let array =
                mat_file::read_variable(path, "Normal_gt").map_err(|e| read_err(path, e))?;
            let [h, w, 3] = array.dims[..] else {
                return Err(read_err(
                    path,
                    format!("Normal_gt is {:?}, expected H x W x 3", array.dims),
                ));
            };
            Ok(Rgb32FImage::from_fn(w as u32, h as u32, |x, y| {
                let at = |c: usize| array.data[y as usize + h * x as usize + h * w * c] as f32;
                image::Rgb([at(0), at(1), at(2)])
            }))
        }
        _ => Err(read_err(
            path,
            "truth normals must be .exr, .png (0.5 n + 0.5) or .mat (Normal_gt)",
        )),
    }
}

/// Parses `--select`: 1-based indices, comma separated, with ranges `a-b`.
pub fn parse_selection(text: &str, count: usize) -> Result<Vec<usize>, ImageSetError> {
    let mut out = Vec::new();
    for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let bad =
            || ImageSetError::Mismatch(format!("--select: '{part}' is not an index or a-b range"));
        let (a, b) = match part.split_once('-') {
            Some((a, b)) => (
                a.trim().parse().map_err(|_| bad())?,
                b.trim().parse().map_err(|_| bad())?,
            ),
            None => {
                let v: usize = part.parse().map_err(|_| bad())?;
                (v, v)
            }
        };
        for index in a..=b {
            if index == 0 || index > count {
                return Err(ImageSetError::BadSelection { index, count });
            }
            out.push(index - 1);
        }
    }
    Ok(out)
}
