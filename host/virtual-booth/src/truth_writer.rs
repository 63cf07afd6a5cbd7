//! Writes the ground truth of a simulated capture under `truth/` (file names from
//! `capture::truth`), and the contact sheet PNG a person looks at.
//!
//! Conventions: see `capture::truth` (camera-sized images, world frame, mm, camera values).

use std::path::Path;

use image::Rgb32FImage;
use serde::Serialize;

use super::VirtualBoothError;
use super::frame_render::{FrameRadiance, ProjectorTransport, Scene};
use super::subjects::Chessboard;
use mlsss_core::capture::{Pattern, truth};
// The truth is run-length coded: kept with the capture, and mostly background zeros.
use mlsss_core::imageio::{GrayF32, srgb_byte, write_exr_gray_compact, write_exr_rgb_compact};

fn rgb_image(w: u32, h: u32, f: impl Fn(usize) -> [f32; 3]) -> Rgb32FImage {
    Rgb32FImage::from_fn(w, h, |x, y| image::Rgb(f((y * w + x) as usize)))
}

/// Calibration, mask, depth, points, normals and material maps.
pub fn write_geometry(
    dir: &Path,
    booth: &mlsss_core::booth::Booth,
    scene: &Scene,
) -> Result<(), VirtualBoothError> {
    let geo = &scene.geometry;
    let (w, h) = (geo.width, geo.height);
    booth.calibration().save(&truth::calibration(dir))?;
    let mask = image::GrayImage::from_fn(w, h, |x, y| {
        let hit = geo.centre[(y * w + x) as usize].is_some();
        image::Luma([if hit { 255 } else { 0 }])
    });
    let mask_path = truth::mask(dir);
    mask.save(&mask_path)
        .map_err(|source| mlsss_core::imageio::ImageIoError::Png {
            path: mask_path,
            source,
        })?;
    let extr = &scene.camera.calib.extrinsics;
    let depth = GrayF32 {
        width: w,
        height: h,
        data: geo
            .centre
            .iter()
            .map(|hit| hit.map_or(0.0, |hit| extr.world_to_device(&hit.point).z as f32))
            .collect(),
    };
    write_exr_gray_compact(&truth::depth(dir), &depth)?;
    let points = rgb_image(w, h, |i| {
        geo.centre[i].map_or([0.0; 3], |hit| hit.point.coords.map(|v| v as f32).into())
    });
    write_exr_rgb_compact(&truth::points(dir), &points)?;
    let normals = rgb_image(w, h, |i| {
        geo.centre[i].map_or([0.0; 3], |hit| hit.normal.map(|v| v as f32).into())
    });
    write_exr_rgb_compact(&truth::normals(dir), &normals)?;
    write_exr_rgb_compact(
        &truth::material_maps(dir),
        &rgb_image(w, h, |i| geo.materials[i]),
    )?;
    Ok(())
}

/// Projector coordinates seen through `view` (camera-sized `(w, h)`).
pub fn write_projector_coords(
    dir: &Path,
    view: &ProjectorTransport,
    (w, h): (u32, u32),
) -> Result<(), VirtualBoothError> {
    write_exr_rgb_compact(
        &truth::projector_coords(dir, view.k),
        &rgb_image(w, h, |i| view.coords[i]),
    )?;
    Ok(())
}

/// Direct and global truth of projector `k` under `pattern`.
pub fn write_components(
    dir: &Path,
    k: usize,
    pattern: &Pattern,
    frame: &FrameRadiance,
    (w, h): (u32, u32),
) -> Result<(), VirtualBoothError> {
    write_exr_rgb_compact(
        &truth::direct(dir, k, pattern),
        &rgb_image(w, h, |i| [frame.direct[i]; 3]),
    )?;
    write_exr_rgb_compact(
        &truth::global(dir, k, pattern),
        &rgb_image(w, h, |i| frame.global_at(i)),
    )?;
    Ok(())
}

/// Light added by the other projectors' black level to projector `k`'s frames.
pub fn write_stray(
    dir: &Path,
    k: usize,
    stray: &[[f32; 3]],
    (w, h): (u32, u32),
) -> Result<(), VirtualBoothError> {
    write_exr_rgb_compact(&truth::stray_light(dir, k), &rgb_image(w, h, |i| stray[i]))?;
    Ok(())
}

/// The calibration target's description and true corner pixels.
#[derive(Debug, Serialize)]
struct TargetTruth<'a> {
    board: &'a Chessboard,
    /// Inner corners, world mm, row by row (OpenCV order).
    corners_world: Vec<[f64; 3]>,
    /// The same corners in the camera image (distortion applied), pixels; null when behind.
    corners_camera_px: Vec<Option<[f64; 2]>>,
}

pub fn write_target(
    dir: &Path,
    scene: &Scene,
    board: &Chessboard,
) -> Result<(), VirtualBoothError> {
    let corners = board.inner_corner_points();
    let truth = TargetTruth {
        board,
        corners_world: corners.iter().map(|p| [p.x, p.y, p.z]).collect(),
        corners_camera_px: corners
            .iter()
            .map(|p| scene.camera.calib.project(p).map(|q| [q.x, q.y]))
            .collect(),
    };
    write_json(&truth::target(dir), &truth)
}

/// Writes a value as pretty JSON.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), VirtualBoothError> {
    let text = serde_json::to_string_pretty(value).map_err(VirtualBoothError::Json)?;
    mlsss_core::atomic_file::write_bytes_atomically(path, text).map_err(|source| {
        VirtualBoothError::Io {
            path: path.to_owned(),
            source,
        }
    })
}

/// Tiles images (linear camera values) into one 8-bit sRGB PNG, `columns` per row, each tile
/// downscaled by box filtering to at most `tile_width` pixels wide.
pub fn write_contact_sheet(
    path: &Path,
    tiles: &[Rgb32FImage],
    columns: usize,
    tile_width: u32,
) -> Result<(), VirtualBoothError> {
    let Some(first) = tiles.first() else {
        return Ok(());
    };
    let factor = first.width().div_ceil(tile_width).max(1);
    let (tw, th) = (first.width() / factor, first.height() / factor);
    let rows = tiles.len().div_ceil(columns);
    let gap = 4;
    let sheet_w = columns as u32 * (tw + gap) + gap;
    let sheet_h = rows as u32 * (th + gap) + gap;
    let mut sheet = image::RgbImage::from_pixel(sheet_w, sheet_h, image::Rgb([40, 40, 40]));
    for (t, tile) in tiles.iter().enumerate() {
        let (ox, oy) = (
            gap + (t % columns) as u32 * (tw + gap),
            gap + (t / columns) as u32 * (th + gap),
        );
        for y in 0..th {
            for x in 0..tw {
                let mut acc = [0.0f32; 3];
                for dy in 0..factor {
                    for dx in 0..factor {
                        let p = tile.get_pixel(x * factor + dx, y * factor + dy).0;
                        for c in 0..3 {
                            acc[c] += p[c];
                        }
                    }
                }
                let n = (factor * factor) as f32;
                let px = acc.map(|v| srgb_byte(v / n));
                sheet.put_pixel(ox + x, oy + y, image::Rgb(px));
            }
        }
    }
    sheet
        .save(path)
        .map_err(|source| mlsss_core::imageio::ImageIoError::Png {
            path: path.to_owned(),
            source,
        })?;
    Ok(())
}
