//! Loading the Gray-code frames of one projector for [`super::gray_code::decode`], from our
//! capture folders (`capture::Capture` + `FramePlan`) or from OpenCV-ordered sequences
//! (DESIGN section 9: per bit, coarse to fine, the pattern then its inverse; all column bits, then
//! all row bits; then white and black), e.g. the real `procam-calibration` set.
//!
//! Conventions: frames are reduced to one channel, the mean of R, G and B, linear in [0, 1].

use std::path::{Path, PathBuf};

use image::Rgb32FImage;
use rayon::prelude::*;

use super::gray_code::{BitPair, GrayCodeFrames, bits_for};
use mlsss_core::capture::{Axis, Capture, CaptureError, Pattern};

/// Errors loading Gray-code frames.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CodeFramesError {
    /// A frame of a capture folder could not be read.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// The capture's frame plan has no such projector.
    #[error("the capture has no projector {projector} (it has {count})")]
    NoSuchProjector { projector: usize, count: usize },
    /// The capture's frame plan lacks a frame the decoder needs.
    #[error("the capture's frame plan has no `{pattern}` frame for projector {projector}")]
    MissingPattern { projector: usize, pattern: String },
    /// A folder could not be listed.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// An OpenCV-ordered folder has the wrong number of frames.
    #[error(
        "{dir}: found {found} PNG frames, an OpenCV Gray-code sequence for a {width}x{height} \
         projector has {expected} (2 x {bits} bit frames, then white and black); check \
         --projector and that no frame is missing or extra"
    )]
    FrameCount {
        dir: PathBuf,
        found: usize,
        expected: usize,
        bits: u32,
        width: u32,
        height: u32,
    },
    /// A frame could not be decoded.
    #[error("{path}: {source}")]
    Image {
        path: PathBuf,
        source: image::ImageError,
    },
    /// Frames of one sequence differ in size.
    #[error(
        "{path} is {width}x{height}, the first frame of the sequence is {first_width}x{first_height}"
    )]
    SizeMismatch {
        path: PathBuf,
        width: u32,
        height: u32,
        first_width: u32,
        first_height: u32,
    },
}

/// The Gray-code frames (plus white, and black when captured) of projector `k` of a capture.
pub fn from_capture(capture: &Capture, k: usize) -> Result<GrayCodeFrames, CodeFramesError> {
    from_capture_reusing(capture, k, None)
}

/// [`from_capture`], read into the buffers of `spare` (frames no longer needed, e.g. the previous
/// projector's) where there are any. Why: each frame read into a fresh buffer came from the
/// system as new zeroed pages, and their page faults were a visible share of the decode stage.
pub fn from_capture_reusing(
    capture: &Capture,
    k: usize,
    spare: Option<GrayCodeFrames>,
) -> Result<GrayCodeFrames, CodeFramesError> {
    let booth = &capture.manifest.booth;
    if k >= booth.projectors.len() {
        return Err(CodeFramesError::NoSuchProjector {
            projector: k,
            count: booth.projectors.len(),
        });
    }
    let spec = &booth.patterns;
    let plan = &capture.manifest.plan;
    let index_of = |pattern: Pattern| {
        plan.find(k as u8, &pattern)
            .map(|f| f.index)
            .ok_or_else(|| CodeFramesError::MissingPattern {
                projector: k,
                pattern: pattern.label(),
            })
    };
    let mut wanted = vec![index_of(Pattern::White)?];
    let black = plan.find(k as u8, &Pattern::Black).map(|f| f.index);
    wanted.extend(black);
    for (axis, bits) in [(Axis::X, spec.gray_bits_x), (Axis::Y, spec.gray_bits_y)] {
        for bit in (0..bits).rev() {
            for inverted in [false, true] {
                wanted.push(index_of(Pattern::Gray {
                    axis,
                    bit,
                    inverted,
                })?);
            }
        }
    }
    let mut buffers = spare.map(GrayCodeFrames::into_buffers).unwrap_or_default();
    buffers.resize_with(wanted.len(), Vec::new);
    let mut frames: Vec<Vec<f32>> = wanted
        .par_iter()
        .zip(buffers)
        .map(|(&index, mut buffer)| {
            capture
                .read_frame_luminance_into(index, &mut buffer)
                .map(|()| buffer)
        })
        .collect::<Result<_, CaptureError>>()?;
    let white = frames.remove(0);
    let black = black.map(|_| frames.remove(0));
    let x_len = 2 * spec.gray_bits_x as usize;
    let y_frames = frames.split_off(x_len);
    Ok(GrayCodeFrames {
        width: booth.camera.width,
        height: booth.camera.height,
        white: Some(white),
        black,
        x: pairs(frames),
        y: pairs(y_frames),
    })
}

/// The frames of an OpenCV-ordered folder (`*.png` sorted by name) for a projector of
/// `projector_size`: `2 * (bits_x + bits_y)` code frames, then white and black (both optional
/// together). 8- or 16-bit, grey or colour.
pub fn from_opencv_dir(
    dir: &Path,
    projector_size: (u32, u32),
) -> Result<GrayCodeFrames, CodeFramesError> {
    let files = png_files(dir)?;
    let (bx, by) = (bits_for(projector_size.0), bits_for(projector_size.1));
    let code_frames = 2 * (bx + by) as usize;
    let has_white_black = match files.len() {
        n if n == code_frames + 2 => true,
        n if n == code_frames => false,
        found => {
            return Err(CodeFramesError::FrameCount {
                dir: dir.to_owned(),
                found,
                expected: code_frames + 2,
                bits: bx + by,
                width: projector_size.0,
                height: projector_size.1,
            });
        }
    };
    let images: Vec<(u32, u32, Vec<f32>)> = files
        .par_iter()
        .map(|path| read_luminance(path))
        .collect::<Result<_, _>>()?;
    let (first_width, first_height) = (images[0].0, images[0].1);
    if let Some((path, (w, h, _))) = files
        .iter()
        .zip(&images)
        .find(|(_, (w, h, _))| (*w, *h) != (first_width, first_height))
    {
        return Err(CodeFramesError::SizeMismatch {
            path: path.clone(),
            width: *w,
            height: *h,
            first_width,
            first_height,
        });
    }
    let mut frames: Vec<Vec<f32>> = images.into_iter().map(|(_, _, f)| f).collect();
    let (white, black) = if has_white_black {
        let black = frames.pop();
        (frames.pop(), black)
    } else {
        (None, None)
    };
    let y_frames = frames.split_off(2 * bx as usize);
    Ok(GrayCodeFrames {
        width: first_width,
        height: first_height,
        white,
        black,
        x: pairs(frames),
        y: pairs(y_frames),
    })
}

/// The `*.png` files of a folder, sorted by name.
pub fn png_files(dir: &Path) -> Result<Vec<PathBuf>, CodeFramesError> {
    let io = |source| CodeFramesError::Io {
        path: dir.to_owned(),
        source,
    };
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")))
        .collect();
    files.sort();
    Ok(files)
}

/// Reads any PNG as one linear channel in [0, 1] (mean of the colour channels).
pub fn read_luminance(path: &Path) -> Result<(u32, u32, Vec<f32>), CodeFramesError> {
    let img = image::open(path).map_err(|source| CodeFramesError::Image {
        path: path.to_owned(),
        source,
    })?;
    let (w, h) = (img.width(), img.height());
    let data = match img {
        image::DynamicImage::ImageLuma8(g) => {
            g.into_raw().iter().map(|&v| v as f32 / 255.0).collect()
        }
        image::DynamicImage::ImageLuma16(g) => {
            g.into_raw().iter().map(|&v| v as f32 / 65535.0).collect()
        }
        other => luminance(&other.into_rgb32f()),
    };
    Ok((w, h, data))
}

/// Mean of the R, G and B channels.
pub fn luminance(img: &Rgb32FImage) -> Vec<f32> {
    img.as_raw()
        .chunks_exact(3)
        .map(|p| (p[0] + p[1] + p[2]) / 3.0)
        .collect()
}

/// Consecutive frames as (pattern, inverse) pairs.
fn pairs(frames: Vec<Vec<f32>>) -> Vec<BitPair> {
    let mut out = Vec::with_capacity(frames.len() / 2);
    let mut it = frames.into_iter();
    while let (Some(pattern), Some(inverse)) = (it.next(), it.next()) {
        out.push(BitPair { pattern, inverse });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::gray_code::{DecodeParams, decode};

    /// The real procam-calibration set: `$MLSSS_DATA`, or `shared/data` beside the repository
    /// (where CI has it). Missing data fails the test: it must not pass without looking.
    fn procam() -> PathBuf {
        [
            std::env::var_os("MLSSS_DATA").map(PathBuf::from),
            Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data")),
            Some(PathBuf::from("/work/shared/data")),
        ]
        .into_iter()
        .flatten()
        .map(|d| d.join("procam-calibration/sample_data"))
        .find(|d| d.is_dir())
        .expect(
            "the real data set shared/data/procam-calibration must be beside the repository \
             (or set MLSSS_DATA to its data folder)",
        )
    }

    #[test]
    fn opencv_pattern_files_are_our_gray_code_in_opencv_order() {
        let dir = procam();
        let files = png_files(&dir.join("graycode_pattern")).unwrap();
        assert_eq!(files.len(), 42);
        let checks = [
            (
                0,
                Pattern::Gray {
                    axis: Axis::X,
                    bit: 9,
                    inverted: false,
                },
            ),
            (
                1,
                Pattern::Gray {
                    axis: Axis::X,
                    bit: 9,
                    inverted: true,
                },
            ),
            (
                18,
                Pattern::Gray {
                    axis: Axis::X,
                    bit: 0,
                    inverted: false,
                },
            ),
            (
                23,
                Pattern::Gray {
                    axis: Axis::Y,
                    bit: 8,
                    inverted: true,
                },
            ),
            (
                38,
                Pattern::Gray {
                    axis: Axis::Y,
                    bit: 0,
                    inverted: false,
                },
            ),
            (40, Pattern::White),
            (41, Pattern::Black),
        ];
        for (index, pattern) in checks {
            let (w, h, data) = read_luminance(&files[index]).unwrap();
            assert_eq!((w, h), (1024, 768));
            let expected = pattern.render(w, h);
            let mismatches = data
                .iter()
                .zip(&expected)
                .filter(|(a, b)| (*a - *b).abs() > 0.01)
                .count();
            assert_eq!(mismatches, 0, "{} vs {pattern:?}", files[index].display());
        }
    }

    #[test]
    fn real_opencv_capture_decodes_with_codes_increasing_across_the_image() {
        let dir = procam();
        let frames = from_opencv_dir(&dir.join("capture_0"), (1024, 768)).unwrap();
        assert_eq!((frames.width, frames.height), (1280, 1024));
        // The centre of the board (the full image takes too long for the test budget).
        let frames = frames.crop(440, 360, 400, 300);
        let decoded = decode(&frames, (1024, 768), &DecodeParams::for_8_bit()).unwrap();
        let summary = decoded.summary();
        eprintln!("{summary:?} valid {:.3}", summary.valid_fraction());
        assert!(summary.valid_fraction() > 0.5, "{summary:?}");
        // Camera and projector sit side by side with nearly the same orientation (the reference
        // rotation is ~identity): the column grows to the right, the row grows downwards.
        let w = frames.width as usize;
        let (mut du, mut dv) = (Vec::new(), Vec::new());
        for i in (0..decoded.u.code.len() - w - 1).step_by(97) {
            if let (Some(a), Some(b), Some(c)) = (
                decoded.coords(i),
                decoded.coords(i + 1),
                decoded.coords(i + w),
            ) {
                du.push(b.0 - a.0);
                dv.push(c.1 - a.1);
            }
        }
        let median = |v: &mut Vec<f32>| {
            v.sort_by(f32::total_cmp);
            v[v.len() / 2]
        };
        let (mdu, mdv) = (median(&mut du), median(&mut dv));
        eprintln!("median du/dx {mdu}, dv/dy {mdv}");
        assert!(mdu > 0.2 && mdv > 0.2, "{mdu} {mdv}");
    }

    #[test]
    fn opencv_folder_with_a_missing_frame_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        for i in 0..41 {
            image::GrayImage::new(4, 3)
                .save(dir.path().join(format!("graycode_{i:02}.png")))
                .unwrap();
        }
        let err = from_opencv_dir(dir.path(), (1024, 768)).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("found 41") && msg.contains("has 42"), "{msg}");
    }
}
