//! Measuring one calibration pose from its frames: chessboard corners in the camera image lit by
//! the projectors' white, Gray-code decoding of every projector (the decoder of
//! [`crate::geometry::gray_code`]), and each corner's projector pixel by a local homography.
//!
//! Two folder layouts are read:
//! - our capture folders (`capture.json` of kind `calibration`, [`mlsss_core::capture::FramePlan::calibration`]):
//!   every projector's white frames are summed for the board (even light, no projector's shadow
//!   hides a corner) and each projector is decoded separately;
//! - OpenCV-ordered sequences (`graycode_NN.png`: the code frames, then white, then black) of one
//!   projector of a given size.
//!
//! A board that is not found is not an error here: the pose comes back with the reason, so the
//! calibration can report it as skipped.

use std::path::{Path, PathBuf};

use nalgebra::Vector2;

use super::chessboard::{DetectorOptions, find_chessboard_corners};
use super::local_homography::{LocalHomographyOptions, projector_corner};
use super::procam::{ImageSize, PoseCorners};
use crate::geometry::code_frames::{self, CodeFramesError};
use crate::geometry::gray_code::{
    BitPair, DecodeParams, GrayCodeError, GrayCodeFrames, ProjectorDecode, decode,
};
use mlsss_core::capture::folder::CaptureKind;
use mlsss_core::capture::{Capture, CaptureError};
use mlsss_core::imageio::GrayF32;
use rayon::prelude::*;

/// Why a pose folder could not be measured.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PoseMeasurementError {
    /// The capture folder could not be opened.
    #[error("pose {dir}: {source}")]
    Capture { dir: PathBuf, source: CaptureError },
    /// The capture folder is a scan, not a calibration pose.
    #[error(
        "pose {dir}: capture.json says kind `scan`; calibration needs captures made with the calibration frame plan"
    )]
    NotCalibration { dir: PathBuf },
    /// The frames could not be loaded (missing or extra frames, sizes, unreadable files).
    #[error("pose {dir}: {source}")]
    Frames {
        dir: PathBuf,
        source: CodeFramesError,
    },
    /// A sequence has no white frame to find the board in.
    #[error(
        "pose {dir}: the sequence has no white frame (OpenCV layout: the code frames, then white, then black)"
    )]
    NoWhite { dir: PathBuf },
}

/// Where the frames of a pose come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseLayout {
    /// Our capture folders, all projectors of the booth.
    Capture,
    /// An OpenCV-ordered sequence of one projector of this size.
    OpenCv { projector: (u32, u32) },
}

/// A measured pose with the image sizes it was measured at.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasuredPose {
    pub corners: PoseCorners,
    pub camera_size: ImageSize,
    pub projector_sizes: Vec<ImageSize>,
}

/// Board size in inner corners.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoardCorners {
    pub cols: usize,
    pub rows: usize,
}

/// Measures one pose folder.
pub fn measure_pose(
    dir: &Path,
    layout: PoseLayout,
    board: BoardCorners,
    local: &LocalHomographyOptions,
) -> Result<MeasuredPose, PoseMeasurementError> {
    let frames_err = |source| PoseMeasurementError::Frames {
        dir: dir.to_owned(),
        source,
    };
    let (sequences, sizes, params) = match layout {
        PoseLayout::OpenCv { projector } => {
            let frames = code_frames::from_opencv_dir(dir, projector).map_err(frames_err)?;
            (vec![frames], vec![projector], DecodeParams::for_8_bit())
        }
        PoseLayout::Capture => {
            let capture = Capture::open(dir).map_err(|source| PoseMeasurementError::Capture {
                dir: dir.to_owned(),
                source,
            })?;
            if capture.manifest.kind != CaptureKind::Calibration {
                return Err(PoseMeasurementError::NotCalibration {
                    dir: dir.to_owned(),
                });
            }
            let booth = &capture.manifest.booth;
            let sequences = (0..booth.projectors.len())
                .map(|k| code_frames::from_capture(&capture, k))
                .collect::<Result<Vec<_>, _>>()
                .map_err(frames_err)?;
            let sizes = booth
                .projectors
                .iter()
                .map(|p| (p.width, p.height))
                .collect();
            let params = if capture.manifest.bit_depth <= 8 {
                DecodeParams::for_8_bit()
            } else {
                DecodeParams::default()
            };
            (sequences, sizes, params)
        }
    };
    let first = &sequences[0];
    let camera_size = ImageSize {
        width: first.width,
        height: first.height,
    };
    let white = summed_white(&sequences).ok_or_else(|| PoseMeasurementError::NoWhite {
        dir: dir.to_owned(),
    })?;
    let camera =
        find_chessboard_corners(&white, board.cols, board.rows, &DetectorOptions::default())
            .map(|c| c.into_iter().map(|p| p.coords).collect::<Vec<_>>())
            .map_err(|e| e.to_string());
    let projectors = match &camera {
        Ok(corners) => sequences
            .iter()
            .zip(&sizes)
            .map(|(frames, &size)| projector_corners(frames, size, &params, corners, local))
            .collect(),
        Err(_) => vec![Vec::new(); sequences.len()],
    };
    Ok(MeasuredPose {
        corners: PoseCorners {
            name: dir.display().to_string(),
            camera,
            projectors,
        },
        camera_size,
        projector_sizes: sizes
            .iter()
            .map(|&(width, height)| ImageSize { width, height })
            .collect(),
    })
}

/// The sum of the white frames of all sequences (`None` if one has no white frame).
fn summed_white(sequences: &[GrayCodeFrames]) -> Option<GrayF32> {
    let first = sequences.first()?;
    let mut sum = GrayF32::new(first.width, first.height);
    for frames in sequences {
        let white = frames.white.as_ref()?;
        if white.len() != sum.data.len() {
            return None;
        }
        for (s, w) in sum.data.iter_mut().zip(white) {
            *s += *w;
        }
    }
    Some(sum)
}

/// Each corner's projector pixel, `None` where it could not be measured (a projector that lights
/// nothing, or a corner in its shadow, gives `None`s, which the calibration reports). Only a
/// window around each corner is decoded: the rest of the frame is not needed, and decoding whole
/// frames would cost ten times more.
fn projector_corners(
    frames: &GrayCodeFrames,
    size: (u32, u32),
    params: &DecodeParams,
    corners: &[Vector2<f64>],
    local: &LocalHomographyOptions,
) -> Vec<Option<Vector2<f64>>> {
    // The decoder's own neighbourhood checks need a margin around the fitting window.
    let margin = local.half_window + params.window_radius as i64 + 2;
    corners
        .par_iter()
        .map(|&corner| {
            let (cx, cy) = (corner.x.round() as i64, corner.y.round() as i64);
            let x0 = (cx - margin).clamp(0, frames.width as i64 - 1);
            let y0 = (cy - margin).clamp(0, frames.height as i64 - 1);
            let x1 = (cx + margin + 1).clamp(x0 + 1, frames.width as i64);
            let y1 = (cy + margin + 1).clamp(y0 + 1, frames.height as i64);
            let window = Window {
                x0: x0 as usize,
                y0: y0 as usize,
                width: (x1 - x0) as usize,
                height: (y1 - y0) as usize,
            };
            let cropped = crop(frames, &window);
            let decoded: Result<ProjectorDecode, GrayCodeError> = decode(&cropped, size, params);
            let decoded = decoded.ok()?;
            let lookup = |x: i64, y: i64| {
                let (lx, ly) = (x - x0, y - y0);
                if lx < 0 || ly < 0 || lx >= window.width as i64 || ly >= window.height as i64 {
                    return None;
                }
                decoded
                    .coords(ly as usize * window.width + lx as usize)
                    .map(|(u, v)| (u as f64, v as f64))
            };
            projector_corner(corner, lookup, local)
        })
        .collect()
}

/// A rectangle of camera pixels.
#[derive(Debug, Clone, Copy)]
struct Window {
    x0: usize,
    y0: usize,
    width: usize,
    height: usize,
}

fn crop_plane(plane: &[f32], frame_width: usize, w: &Window) -> Vec<f32> {
    (w.y0..w.y0 + w.height)
        .flat_map(|y| {
            plane[y * frame_width + w.x0..y * frame_width + w.x0 + w.width]
                .iter()
                .copied()
        })
        .collect()
}

/// The same sequence restricted to a window.
fn crop(frames: &GrayCodeFrames, w: &Window) -> GrayCodeFrames {
    let fw = frames.width as usize;
    let pairs = |bits: &[BitPair]| {
        bits.iter()
            .map(|b| BitPair {
                pattern: crop_plane(&b.pattern, fw, w),
                inverse: crop_plane(&b.inverse, fw, w),
            })
            .collect()
    };
    GrayCodeFrames {
        width: w.width as u32,
        height: w.height as u32,
        white: frames.white.as_ref().map(|p| crop_plane(p, fw, w)),
        black: frames.black.as_ref().map(|p| crop_plane(p, fw, w)),
        x: pairs(&frames.x),
        y: pairs(&frames.y),
    }
}
