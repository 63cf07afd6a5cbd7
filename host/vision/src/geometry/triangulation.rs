//! Triangulation of decoded projector coordinates and robust fusion across projectors.
//!
//! Conventions
//! - World frame in millimetres (the calibration's); extrinsics `x_device = R x_world + t`.
//! - Camera pixel `(x, y)` centres at integers, origin top-left; projector `(u, v)` likewise.
//! - Depth is the camera-frame `z` (mm) of the surface point; 0 where nothing was measured (as the
//!   simulator's `truth/depth.exr`).
//!
//! Each camera pixel's ray is intersected with the ray of the projector pixel `(u, v)` it decoded
//! (both coordinates, so lens distortion of either device is handled). The camera ray is exact
//! (the pixel centre) while `(u, v)` carries the decoding error, so the point kept is the one on
//! the camera ray closest to the projector ray; the gap between the rays measures how well the
//! pair agrees with the calibration and rejects bad decodes. With several projectors, depths are
//! fused robustly: the median, then the mean of the depths within `fuse_tolerance_mm` of it.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use mlsss_core::calibration::DeviceCalibration;

/// Thresholds of triangulation and fusion.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TriangulationParams {
    /// Largest distance between the camera ray and the projector ray, mm.
    pub max_ray_gap_mm: f64,
    /// Depths farther than this from the per-pixel median are outliers, mm.
    pub fuse_tolerance_mm: f64,
}

impl Default for TriangulationParams {
    fn default() -> Self {
        Self {
            max_ray_gap_mm: 1.0,
            fuse_tolerance_mm: 1.0,
        }
    }
}

/// One projector's decoded coordinates and calibration.
#[derive(Debug, Clone, Copy)]
pub struct DecodedProjector<'a> {
    pub calibration: &'a DeviceCalibration,
    /// `Some((u, v))` per camera pixel, row-major.
    pub coords: &'a [Option<(f64, f64)>],
}

/// The fused surface seen by the camera.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    pub width: u32,
    pub height: u32,
    /// Camera-frame z, mm; 0 where not measured.
    pub depth: Vec<f32>,
    /// World-frame point, mm; zeros where not measured.
    pub points: Vec<[f32; 3]>,
    /// Projectors whose depth was kept at each pixel.
    pub projectors_used: Vec<u8>,
    /// Projector depths rejected as outliers at each pixel.
    pub outliers: Vec<u8>,
}

impl DepthMap {
    /// True where a depth was measured.
    pub fn is_valid(&self, i: usize) -> bool {
        self.depth[i] > 0.0
    }

    pub fn valid_count(&self) -> usize {
        self.depth.iter().filter(|d| **d > 0.0).count()
    }
}

/// Point on the camera ray `(o1, d1)` closest to the projector ray `(o2, d2)`, with the gap between
/// the rays; `None` for (nearly) parallel rays or a point behind either device.
pub fn closest_point_on_first_ray(
    o1: &Point3<f64>,
    d1: &Vector3<f64>,
    o2: &Point3<f64>,
    d2: &Vector3<f64>,
) -> Option<(Point3<f64>, f64)> {
    let w = o1 - o2;
    let (a, b, c) = (d1.dot(d1), d1.dot(d2), d2.dot(d2));
    let (d, e) = (d1.dot(&w), d2.dot(&w));
    let denom = a * c - b * b;
    if denom.abs() < 1e-12 * a * c {
        return None;
    }
    let s = (b * e - c * d) / denom;
    let t = (a * e - b * d) / denom;
    if s <= 0.0 || t <= 0.0 {
        return None;
    }
    let p1 = o1 + d1 * s;
    let p2 = o2 + d2 * t;
    Some((p1, (p1 - p2).norm()))
}

/// Triangulates every camera pixel against every projector and fuses the results.
pub fn triangulate(
    camera: &DeviceCalibration,
    views: &[DecodedProjector],
    params: &TriangulationParams,
) -> DepthMap {
    let (w, h) = (camera.width, camera.height);
    let n = w as usize * h as usize;
    let results: Vec<(f32, [f32; 3], u8, u8)> = (0..n)
        .into_par_iter()
        .map(|i| {
            let (x, y) = ((i % w as usize) as f64, (i / w as usize) as f64);
            fuse_pixel(camera, views, i, x, y, params)
        })
        .collect();
    let mut map = DepthMap {
        width: w,
        height: h,
        depth: Vec::with_capacity(n),
        points: Vec::with_capacity(n),
        projectors_used: Vec::with_capacity(n),
        outliers: Vec::with_capacity(n),
    };
    for (d, p, used, out) in results {
        map.depth.push(d);
        map.points.push(p);
        map.projectors_used.push(used);
        map.outliers.push(out);
    }
    map
}

fn fuse_pixel(
    camera: &DeviceCalibration,
    views: &[DecodedProjector],
    i: usize,
    x: f64,
    y: f64,
    params: &TriangulationParams,
) -> (f32, [f32; 3], u8, u8) {
    let nothing = (0.0, [0.0; 3], 0, 0);
    if views
        .iter()
        .all(|v| v.coords.get(i).copied().flatten().is_none())
    {
        return nothing;
    }
    let (o1, d1) = camera.ray(x, y);
    let mut candidates: Vec<(f64, Point3<f64>)> = Vec::with_capacity(views.len());
    let mut rejected = 0u8;
    for view in views {
        let Some((u, v)) = view.coords.get(i).copied().flatten() else {
            continue;
        };
        let (o2, d2) = view.calibration.ray(u, v);
        match closest_point_on_first_ray(&o1, &d1, &o2, &d2) {
            Some((p, gap)) if gap <= params.max_ray_gap_mm => {
                let z = camera.extrinsics.world_to_device(&p).z;
                candidates.push((z, p));
            }
            _ => rejected += 1,
        }
    }
    if candidates.is_empty() {
        return (0.0, [0.0; 3], 0, rejected);
    }
    let mut depths: Vec<f64> = candidates.iter().map(|c| c.0).collect();
    depths.sort_by(f64::total_cmp);
    let median = if depths.len() % 2 == 1 {
        depths[depths.len() / 2]
    } else {
        0.5 * (depths[depths.len() / 2 - 1] + depths[depths.len() / 2])
    };
    let inliers: Vec<&(f64, Point3<f64>)> = candidates
        .iter()
        .filter(|c| (c.0 - median).abs() <= params.fuse_tolerance_mm)
        .collect();
    let outliers = rejected + (candidates.len() - inliers.len()) as u8;
    if inliers.is_empty() {
        // Two projectors that disagree: no way to tell which is right, flag the pixel.
        return (0.0, [0.0; 3], 0, outliers);
    }
    let k = inliers.len() as f64;
    let z = inliers.iter().map(|c| c.0).sum::<f64>() / k;
    let p = inliers
        .iter()
        .fold(Vector3::zeros(), |acc, c| acc + c.1.coords)
        / k;
    (
        z as f32,
        [p.x as f32, p.y as f32, p.z as f32],
        inliers.len() as u8,
        outliers,
    )
}

/// Depth error statistics against a true depth map (same size; 0 = no surface).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DepthErrors {
    pub depth_rmse_mm: f64,
    pub depth_p95_abs_mm: f64,
    pub depth_mean_abs_mm: f64,
    /// Measured pixels over pixels with a true surface.
    pub coverage: f64,
    /// Measured pixels with no true surface, over measured pixels.
    pub spurious_fraction: f64,
}

impl DepthErrors {
    pub fn new(map: &DepthMap, truth_depth: &[f32]) -> Self {
        let mut errors = Vec::new();
        let (mut surface, mut spurious, mut measured) = (0usize, 0usize, 0usize);
        for (i, &t) in truth_depth.iter().enumerate().take(map.depth.len()) {
            let m = map.depth[i];
            if t > 0.0 {
                surface += 1;
            }
            if m > 0.0 {
                measured += 1;
                if t > 0.0 {
                    errors.push((m - t).abs() as f64);
                } else {
                    spurious += 1;
                }
            }
        }
        let n = errors.len().max(1) as f64;
        let rmse = (errors.iter().map(|e| e * e).sum::<f64>() / n).sqrt();
        let mean = errors.iter().sum::<f64>() / n;
        errors.sort_by(f64::total_cmp);
        let p95 = errors
            .get(((errors.len() as f64 * 0.95) as usize).min(errors.len().saturating_sub(1)))
            .copied()
            .unwrap_or(0.0);
        Self {
            depth_rmse_mm: rmse,
            depth_p95_abs_mm: p95,
            depth_mean_abs_mm: mean,
            coverage: errors.len() as f64 / surface.max(1) as f64,
            spurious_fraction: spurious as f64 / measured.max(1) as f64,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::booth::Booth;

    /// Exact projector coordinates of a plane z = z0 (world) seen by the camera: what a perfect
    /// decoder would return.
    fn plane_coords(booth: &Booth, k: usize, z0: f64) -> Vec<Option<(f64, f64)>> {
        let cam = booth.camera_calibration();
        let proj = booth.projector_calibration(k).unwrap();
        (0..cam.height)
            .flat_map(|y| (0..cam.width).map(move |x| (x, y)))
            .map(|(x, y)| {
                let (o, d) = cam.ray(x as f64, y as f64);
                let s = (z0 - o.z) / d.z;
                let p = o + d * s;
                proj.project(&p)
                    .filter(|q| {
                        q.x > -0.5
                            && q.y > -0.5
                            && q.x < proj.width as f64
                            && q.y < proj.height as f64
                    })
                    .map(|q| (q.x, q.y))
            })
            .collect()
    }

    #[test]
    fn exact_coordinates_of_a_plane_give_its_depth_and_outliers_are_rejected() {
        let booth = Booth::builtin(true);
        let calib = booth.calibration();
        let z0 = 10.0;
        let mut coords: Vec<Vec<Option<(f64, f64)>>> =
            (0..4).map(|k| plane_coords(&booth, k, z0)).collect();
        // Projector 3 decodes garbage on a block of pixels: fusion must reject it.
        let w = booth.camera.width as usize;
        for y in 100..140 {
            for x in 200..260 {
                if let Some(c) = coords[3][y * w + x].as_mut() {
                    c.0 += 25.0;
                }
            }
        }
        let views: Vec<DecodedProjector> = calib
            .projectors
            .iter()
            .zip(&coords)
            .map(|(p, c)| DecodedProjector {
                calibration: &p.device,
                coords: c,
            })
            .collect();
        let map = triangulate(&calib.camera, &views, &TriangulationParams::default());
        let cam = &calib.camera;
        let mut worst: f64 = 0.0;
        for i in 0..map.depth.len() {
            if !map.is_valid(i) {
                continue;
            }
            let p = Point3::new(
                map.points[i][0] as f64,
                map.points[i][1] as f64,
                map.points[i][2] as f64,
            );
            worst = worst.max((p.z - z0).abs());
            // The depth is the camera-frame z of the point.
            let zc = cam.extrinsics.world_to_device(&p).z;
            assert!((zc - map.depth[i] as f64).abs() < 1e-3);
        }
        assert!(worst < 1e-3, "worst {worst}");
        assert!(map.valid_count() > map.depth.len() / 2);
        let i = 120 * w + 230;
        assert!(map.is_valid(i));
        assert_eq!(map.outliers[i], 1, "the shifted projector is the outlier");
        assert_eq!(map.projectors_used[i], 3);
    }

    #[test]
    fn parallel_rays_do_not_triangulate() {
        let o1 = Point3::origin();
        let o2 = Point3::new(10.0, 0.0, 0.0);
        let d = Vector3::new(0.0, 0.0, 1.0);
        assert!(closest_point_on_first_ray(&o1, &d, &o2, &d).is_none());
        let d2 = Vector3::new(-1.0, 0.0, 1.0).normalize();
        let (p, gap) = closest_point_on_first_ray(&o1, &d, &o2, &d2).unwrap();
        assert!((p.z - 10.0).abs() < 1e-9 && gap < 1e-9);
    }
}
