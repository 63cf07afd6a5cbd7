//! A triangle mesh from the camera-pixel grid of a depth map, written as binary PLY, and a shaded
//! preview of it.
//!
//! Conventions: vertices are the measured world points (mm) of valid pixels; each 2x2 block of
//! pixels gives up to two triangles when its corners are measured and no edge is longer than
//! `max_edge_mm` (depth discontinuities are not bridged). Faces wind counter-clockwise as seen
//! from the camera.

use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use super::triangulation::DepthMap;

/// Errors writing a mesh.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GridMeshError {
    /// The file could not be written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// Vertices and triangles of a depth map's pixel grid.
#[derive(Debug, Clone, PartialEq)]
pub struct GridMesh {
    pub vertices: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

impl GridMesh {
    /// Builds the mesh, skipping edges longer than `max_edge_mm`.
    pub fn from_depth_map(map: &DepthMap, max_edge_mm: f32) -> Self {
        let (w, h) = (map.width as usize, map.height as usize);
        let mut index = vec![u32::MAX; w * h];
        let mut vertices = Vec::new();
        for (i, slot) in index.iter_mut().enumerate() {
            if map.is_valid(i) {
                *slot = vertices.len() as u32;
                vertices.push(map.points[i]);
            }
        }
        let close = |a: usize, b: usize| distance(&map.points[a], &map.points[b]) <= max_edge_mm;
        let mut triangles = Vec::new();
        for y in 0..h.saturating_sub(1) {
            for x in 0..w.saturating_sub(1) {
                let (a, b, c, d) = (
                    y * w + x,
                    y * w + x + 1,
                    (y + 1) * w + x,
                    (y + 1) * w + x + 1,
                );
                // Camera y points down, so (a, c, b) is counter-clockwise seen from the camera.
                for tri in [[a, c, b], [b, c, d]] {
                    let ok = tri.iter().all(|&p| index[p] != u32::MAX)
                        && close(tri[0], tri[1])
                        && close(tri[1], tri[2])
                        && close(tri[2], tri[0]);
                    if ok {
                        triangles.push(tri.map(|p| index[p]));
                    }
                }
            }
        }
        Self {
            vertices,
            triangles,
        }
    }

    /// Writes a binary little-endian PLY.
    pub fn write_ply(&self, path: &Path) -> Result<(), GridMeshError> {
        let header = format!(
            "ply\nformat binary_little_endian 1.0\ncomment mlsss geometry, world frame, mm\n\
             element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
             element face {}\nproperty list uchar int vertex_indices\nend_header\n",
            self.vertices.len(),
            self.triangles.len()
        );
        mlsss_core::atomic_file::write_atomically(path, |out| {
            out.write_all(header.as_bytes())?;
            for c in self.vertices.iter().flatten() {
                out.write_all(&c.to_le_bytes())?;
            }
            for t in &self.triangles {
                out.write_all(&[3u8])?;
                for i in t {
                    out.write_all(&(*i as i32).to_le_bytes())?;
                }
            }
            Ok(())
        })
        .map_err(|source| GridMeshError::Io {
            path: path.to_owned(),
            source,
        })
    }
}

fn distance(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// A grey preview: Lambert shading of the surface normals (from the point grid) under a light at
/// the camera, `None` (black) where not measured.
pub fn shaded_preview(map: &DepthMap, camera_centre: [f64; 3]) -> image::GrayImage {
    let (w, h) = (map.width as usize, map.height as usize);
    let at = |x: usize, y: usize| {
        let i = y * w + x;
        map.is_valid(i)
            .then(|| Vector3::from(map.points[i].map(f64::from)))
    };
    let eye = Vector3::from(camera_centre);
    image::GrayImage::from_fn(map.width, map.height, |x, y| {
        let (x, y) = (x as usize, y as usize);
        let (x0, x1) = (x.saturating_sub(1), (x + 1).min(w - 1));
        let (y0, y1) = (y.saturating_sub(1), (y + 1).min(h - 1));
        let shade = (|| {
            let p = at(x, y)?;
            let dx = at(x1, y)? - at(x0, y)?;
            let dy = at(x, y1)? - at(x, y0)?;
            let n = dy.cross(&dx).try_normalize(1e-12)?;
            let l = (eye - p).try_normalize(1e-12)?;
            Some(n.dot(&l).abs())
        })();
        image::Luma([shade.map_or(0, |s| (40.0 + 215.0 * s).round() as u8)])
    })
}
