//! Stage `geometry`: triangulation of the decoded coordinates of every projector and robust fusion
//! (`geometry::triangulation`), mesh and previews (`geometry::grid_mesh`).
//!
//! Artefacts in `OUT/geometry/`:
//! - `depth.exr`: one channel, camera-frame depth z in mm, 0 where not measured (as
//!   `truth/depth.exr`).
//! - `points.exr`: RGB = world-frame X, Y, Z in mm (as `truth/points.exr`).
//! - `point_normals.exr`: RGB = the points' plane-fit unit normals, world frame, 0 where no
//!   point (`geometry::point_normals`); `point_normals_reliable.exr`: one channel, 1 where the
//!   fit is reliable. Fitted once here for the separate stage's lobe and the normals stage's
//!   fusion, which both read them.
//! - `mesh.ply`: binary PLY of the pixel-grid mesh, world frame, mm.
//! - `shaded.png`: Lambert-shaded preview of the surface.
//!
//! Report fragment: `valid_fraction`, `mean_projectors_used`, `outlier_fraction`, `triangles`, and
//! with ground truth `depth_rmse_mm`, `depth_p95_abs_mm`, `depth_mean_abs_mm`, `coverage`,
//! `spurious_fraction`.

use std::path::{Path, PathBuf};

use image::Rgb32FImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::decode_stage::{DecodeStageError, coords_path, load_coords};
use super::{Stage, StageContext, StageFailure, write_side_by_side};
use mlsss_core::capture::truth;
use mlsss_core::imageio::{self, GrayF32, ImageIoError};
use mlsss_vision::geometry::grid_mesh::{GridMesh, GridMeshError, shaded_preview};
use mlsss_vision::geometry::point_normals::{PointNormalParams, PointNormals, fit_point_normals};
use mlsss_vision::geometry::triangulation::{
    DecodedProjector, DepthErrors, DepthMap, TriangulationParams, triangulate,
};

/// The geometry stage.
pub const STAGE: Stage = Stage {
    name: "geometry",
    // 2: the points' plane-fit normals.
    version: 2,
    inputs: &["decode"],
    uses_calibration: true,
    run,
};

/// Parameters of the geometry stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GeometryParams {
    #[serde(flatten)]
    pub triangulation: TriangulationParams,
    /// Longest mesh edge, mm (longer edges are depth discontinuities).
    pub max_edge_mm: f32,
    /// The plane fits of the points' normals.
    pub point_normals: PointNormalParams,
}

impl Default for GeometryParams {
    fn default() -> Self {
        Self {
            triangulation: TriangulationParams::default(),
            max_edge_mm: 3.0,
            point_normals: PointNormalParams::default(),
        }
    }
}

/// The geometry stage's report fragment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GeometryReport {
    /// Camera pixels with a depth.
    pub valid_fraction: f64,
    /// Mean number of projectors fused per measured pixel.
    pub mean_projectors_used: f64,
    /// Candidate depths rejected by the fusion, over all candidates.
    pub outlier_fraction: f64,
    pub triangles: usize,
    /// With ground truth: the depth errors.
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<DepthErrors>,
}

/// Errors of the geometry stage.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GeometryStageError {
    /// The calibration has fewer projectors than the capture.
    #[error("the calibration has {calibrated} projectors, the capture {captured}")]
    ProjectorCount { calibrated: usize, captured: usize },
    /// The calibration's camera size differs from the capture's.
    #[error(
        "the calibration's camera is {calib_width}x{calib_height}, the capture's {width}x{height}"
    )]
    CameraSize {
        calib_width: u32,
        calib_height: u32,
        width: u32,
        height: u32,
    },
    /// No projector was decoded.
    #[error("no projector has decoded coordinates in {0}")]
    NothingDecoded(PathBuf),
    /// Reading decoded coordinates or truth failed.
    #[error(transparent)]
    Decode(#[from] DecodeStageError),
    /// An artefact could not be written.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// The mesh could not be written.
    #[error(transparent)]
    Mesh(#[from] GridMeshError),
}

/// Errors of reading the geometry stage's artefacts (and point maps like them).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GeometryReadError {
    /// A file could not be read.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// A file is not the size the caller's images are.
    #[error("{path} is {got:?}, the images are {expected:?}")]
    Size {
        path: PathBuf,
        got: (u32, u32),
        expected: (u32, u32),
    },
}

/// Path of the surface points in the geometry stage's folder `dir`.
pub fn points_path(dir: &Path) -> PathBuf {
    dir.join("points.exr")
}

/// Path of the points' normals in the geometry stage's folder `dir`.
pub fn point_normals_path(dir: &Path) -> PathBuf {
    dir.join("point_normals.exr")
}

/// Path of the points' normal reliability flags in the geometry stage's folder `dir`.
pub fn point_normals_reliable_path(dir: &Path) -> PathBuf {
    dir.join("point_normals_reliable.exr")
}

/// `Size` unless `got` is `expected`.
fn check_size(path: &Path, got: (u32, u32), expected: (u32, u32)) -> Result<(), GeometryReadError> {
    if got == expected {
        Ok(())
    } else {
        Err(GeometryReadError::Size {
            path: path.to_owned(),
            got,
            expected,
        })
    }
}

/// The point map (RGB = world X, Y, Z in mm) at `path`, checked to be `size`: the geometry
/// stage's [`points_path`] or the simulator's `truth/points.exr`.
pub fn load_points_file(path: &Path, size: (u32, u32)) -> Result<Rgb32FImage, GeometryReadError> {
    let points = imageio::read_exr_rgb(path)?;
    check_size(path, points.dimensions(), size)?;
    Ok(points)
}

/// The points' plane-fit normals the geometry stage in `dir` wrote, checked to be `size`.
pub fn load_point_normals(dir: &Path, size: (u32, u32)) -> Result<PointNormals, GeometryReadError> {
    let path = point_normals_path(dir);
    let (width, height, normals) = imageio::read_exr_rgb_pixels(&path)?;
    check_size(&path, (width, height), size)?;
    let path = point_normals_reliable_path(dir);
    let reliable = imageio::read_exr_gray(&path)?;
    check_size(&path, (reliable.width, reliable.height), size)?;
    Ok(PointNormals {
        width: size.0,
        height: size.1,
        normals,
        reliable: reliable.data.iter().map(|&r| r > 0.5).collect(),
    })
}

fn run(ctx: &StageContext) -> Result<Value, StageFailure> {
    let params: GeometryParams = ctx.params()?;
    super::fragment(&run_geometry(ctx, &params).map_err(StageFailure::new)?)
}

fn run_geometry(
    ctx: &StageContext,
    params: &GeometryParams,
) -> Result<GeometryReport, GeometryStageError> {
    let calib = ctx
        .calibration
        .ok_or(GeometryStageError::NothingDecoded(ctx.stage_dir("decode")))?;
    let cam_spec = &ctx.capture.manifest.booth.camera;
    let size = (cam_spec.width, cam_spec.height);
    if (calib.camera.width, calib.camera.height) != size {
        return Err(GeometryStageError::CameraSize {
            calib_width: calib.camera.width,
            calib_height: calib.camera.height,
            width: size.0,
            height: size.1,
        });
    }
    let captured = ctx.capture.manifest.booth.projectors.len();
    if calib.projectors.len() < captured {
        return Err(GeometryStageError::ProjectorCount {
            calibrated: calib.projectors.len(),
            captured,
        });
    }
    let decode_dir = ctx.stage_dir("decode");
    // One map per thread: reading an EXR is mostly serial.
    let coords = (0..captured)
        .into_par_iter()
        .filter_map(|k| {
            let path = coords_path(&decode_dir, k);
            // A projector skipped by decode (all dark) has no map.
            path.is_file()
                .then(|| load_coords(&path, size).map(|c| (k, c)))
        })
        .collect::<Result<Vec<_>, _>>()?;
    if coords.is_empty() {
        return Err(GeometryStageError::NothingDecoded(decode_dir));
    }
    let views: Vec<DecodedProjector> = coords
        .iter()
        .map(|(k, c)| DecodedProjector {
            calibration: &calib.projectors[*k].device,
            coords: c,
        })
        .collect();
    let map = triangulate(&calib.camera, &views, &params.triangulation);
    let mesh = GridMesh::from_depth_map(&map, params.max_edge_mm);
    let camera_centre = calib.camera.extrinsics.centre();
    // The artefacts are written beside the point normals (their writes are mostly one thread
    // each, the smoothing's passes leave cores idle between them).
    let (written, normals) = rayon::join(
        || write_artefacts(ctx, &map, &mesh, camera_centre.coords.into()),
        || {
            fit_point_normals(
                &map.points,
                map.width,
                map.height,
                camera_centre,
                &params.point_normals,
            )
        },
    );
    written?;
    write_point_normals(&ctx.dir(), &normals)?;

    let truth = match ctx.truth_dir() {
        Some(t) => {
            let truth_depth = imageio::read_exr_gray(&truth::depth(&t))?;
            Some(DepthErrors::new(&map, &truth_depth.data))
        }
        None => None,
    };
    Ok(report(&map, mesh.triangles.len(), truth))
}

fn report(map: &DepthMap, triangles: usize, truth: Option<DepthErrors>) -> GeometryReport {
    let n = map.depth.len().max(1) as f64;
    let valid = map.valid_count();
    let used: usize = map.projectors_used.iter().map(|&u| u as usize).sum();
    let candidates: usize = used + map.outliers.iter().map(|&o| o as usize).sum::<usize>();
    GeometryReport {
        valid_fraction: valid as f64 / n,
        mean_projectors_used: used as f64 / valid.max(1) as f64,
        outlier_fraction: (candidates - used) as f64 / candidates.max(1) as f64,
        triangles,
        truth,
    }
}

fn write_point_normals(dir: &Path, normals: &PointNormals) -> Result<(), ImageIoError> {
    let (width, height) = (normals.width, normals.height);
    let data = normals.normals.iter().flatten().copied().collect();
    // One normal per pixel by construction; an empty image if that ever broke.
    let image = Rgb32FImage::from_raw(width, height, data)
        .unwrap_or_else(|| Rgb32FImage::new(width, height));
    let reliable = GrayF32 {
        width,
        height,
        data: normals
            .reliable
            .iter()
            .map(|&r| f32::from(u8::from(r)))
            .collect(),
    };
    write_side_by_side(vec![
        Box::new(|| imageio::write_exr_rgb(&point_normals_path(dir), &image)),
        Box::new(|| imageio::write_exr_gray(&point_normals_reliable_path(dir), &reliable)),
    ])
}

fn write_artefacts(
    ctx: &StageContext,
    map: &DepthMap,
    mesh: &GridMesh,
    camera_centre: [f64; 3],
) -> Result<(), GeometryStageError> {
    let dir = &ctx.dir();
    write_side_by_side::<GeometryStageError>(vec![
        Box::new(|| {
            let depth = GrayF32 {
                width: map.width,
                height: map.height,
                data: map.depth.clone(),
            };
            Ok(imageio::write_exr_gray(&dir.join("depth.exr"), &depth)?)
        }),
        Box::new(|| {
            let points = Rgb32FImage::from_fn(map.width, map.height, |x, y| {
                image::Rgb(map.points[(y * map.width + x) as usize])
            });
            Ok(imageio::write_exr_rgb(&points_path(dir), &points)?)
        }),
        Box::new(|| Ok(mesh.write_ply(&dir.join("mesh.ply"))?)),
        Box::new(|| {
            let preview = shaded_preview(map, camera_centre);
            Ok(imageio::write_png(&dir.join("shaded.png"), &preview)?)
        }),
    ])
}
