//! Surface normals of a measured point map: at each pixel, the normal of the plane fitted to the
//! points around it by Gaussian-weighted principal component analysis (Hoppe et al. 1992): the
//! eigenvector of the smallest eigenvalue of the points' weighted covariance.
//!
//! Conventions
//! - Points: one per camera pixel, row-major, world frame (mm); a zero or non-finite point is
//!   no point.
//! - Normals: unit, world frame, turned towards `viewpoint` (the camera centre: a surface the
//!   camera sees faces it).
//! - `sigma_px`: standard deviation of the Gaussian window, camera pixels.
//!
//! A fit is *reliable* where the window is nearly full of points (not at a silhouette or a hole)
//! and the points are flat in it (not across a depth step or a crease): there the plane's normal
//! is the surface's, smoothed over the window.

use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_2d_mapped};
use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;

use crate::symmetric_eigen3::smallest_eigenpair;

/// How the planes are fitted.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PointNormalParams {
    /// Gaussian window, camera pixels.
    pub sigma_px: f64,
    /// Least Gaussian-weighted share of the window that must hold points for a reliable fit.
    pub min_support: f64,
    /// Largest ratio of the covariance's smallest to middle eigenvalue of a reliable fit (0 for
    /// points on a plane; a depth step or a crease in the window raises it).
    pub max_flatness: f64,
}

impl Default for PointNormalParams {
    fn default() -> Self {
        Self {
            sigma_px: 1.5,
            min_support: 0.9,
            max_flatness: 0.03,
        }
    }
}

/// The fitted normals of a point map.
#[derive(Debug, Clone, PartialEq)]
pub struct PointNormals {
    pub width: u32,
    pub height: u32,
    /// Unit normal per pixel, zero where the pixel has no point.
    pub normals: Vec<[f32; 3]>,
    /// Whether each pixel's fit is reliable (see the module notes).
    pub reliable: Vec<bool>,
}

/// Weighted moments of the points in a window: `w`, `w p` (3), `w p p^T` (6, upper triangle).
type Moments = [f64; 10];

/// The plane-fit normals of the `width` x `height` point map `points`, turned towards
/// `viewpoint`. A map whose length is not `width * height` gives no normals.
pub fn fit_point_normals(
    points: &[[f32; 3]],
    width: u32,
    height: u32,
    viewpoint: Point3<f64>,
    params: &PointNormalParams,
) -> PointNormals {
    let (w, h) = (width as usize, height as usize);
    if points.len() != w * h {
        return PointNormals {
            width,
            height,
            normals: vec![[0.0; 3]; points.len()],
            reliable: vec![false; points.len()],
        };
    }
    let kernel = GaussianKernel::new(params.sigma_px, 3.0, Normalisation::Weights);
    // The moments blurred band by band on every core (shared with the artefact writes the
    // geometry stage runs beside it), never held whole: the same numbers as blurring them on one
    // thread.
    let normal_of = |i: usize, m: Moments| {
        let Some(point) = surface_point(points[i]) else {
            return ([0.0; 3], false);
        };
        let Some((normal, flatness)) = plane_normal(&m) else {
            return ([0.0; 3], false);
        };
        let normal = if normal.dot(&(viewpoint - point)) < 0.0 {
            -normal
        } else {
            normal
        };
        let reliable = m[0] >= params.min_support && flatness <= params.max_flatness;
        (
            [normal.x as f32, normal.y as f32, normal.z as f32],
            reliable,
        )
    };
    let moments = |i: usize| point_moments(points[i]);
    let (normals, reliable): (Vec<[f32; 3]>, Vec<bool>) =
        blur_2d_mapped(w, h, &kernel, Border::Zero, moments, normal_of)
            .into_par_iter()
            .unzip();
    PointNormals {
        width,
        height,
        normals,
        reliable,
    }
}

/// The point of a pixel, if it has one.
fn surface_point(p: [f32; 3]) -> Option<Point3<f64>> {
    let known = p.iter().all(|v| v.is_finite()) && p.iter().any(|v| *v != 0.0);
    known.then(|| Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
}

/// A pixel's own moments (all zero without a point).
fn point_moments(p: [f32; 3]) -> Moments {
    let Some(q) = surface_point(p) else {
        return [0.0; 10];
    };
    let (x, y, z) = (q.x, q.y, q.z);
    [1.0, x, y, z, x * x, x * y, x * z, y * y, y * z, z * z]
}

/// The unit normal of the plane through a window's moments and its flatness (smallest over
/// middle eigenvalue of the covariance), if the window holds enough spread to fit one.
fn plane_normal(m: &Moments) -> Option<(Vector3<f64>, f64)> {
    let weight = m[0];
    if weight <= f64::EPSILON {
        return None;
    }
    let mean = Vector3::new(m[1], m[2], m[3]) / weight;
    let second = Matrix3::new(
        m[4], m[5], m[6], //
        m[5], m[7], m[8], //
        m[6], m[8], m[9],
    ) / weight;
    let covariance = second - mean * mean.transpose();
    let (smallest, middle, normal) = smallest_eigenpair(&covariance)?;
    if middle <= 0.0 || !middle.is_finite() {
        return None;
    }
    Some((normal, smallest.max(0.0) / middle))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The points a pinhole camera at the origin looking down +z sees of `surface` (depth per
    /// normalised image coordinate), `width` x `height` pixels of pitch `pitch`.
    fn point_map(
        width: u32,
        height: u32,
        pitch: f64,
        depth: impl Fn(f64, f64) -> Option<f64>,
    ) -> Vec<[f32; 3]> {
        let mut points = Vec::new();
        for v in 0..height {
            for u in 0..width {
                let x = (u as f64 - width as f64 / 2.0) * pitch;
                let y = (v as f64 - height as f64 / 2.0) * pitch;
                points.push(match depth(x, y) {
                    Some(z) => [(x * z) as f32, (y * z) as f32, z as f32],
                    None => [0.0; 3],
                });
            }
        }
        points
    }

    fn angle_deg(a: [f32; 3], b: Vector3<f64>) -> f64 {
        let a = Vector3::new(a[0] as f64, a[1] as f64, a[2] as f64).normalize();
        a.dot(&b.normalize()).clamp(-1.0, 1.0).acos().to_degrees()
    }

    #[test]
    fn a_tilted_plane_gets_its_normal_towards_the_camera_everywhere_inside() {
        // Plane n . X = d with n = (0.3, -0.2, -1) (facing the camera at the origin), d = -500.
        let n = Vector3::new(0.3, -0.2, -1.0);
        let depth = |x: f64, y: f64| Some(-500.0 / (n.x * x + n.y * y + n.z));
        let points = point_map(40, 30, 0.002, depth);
        let fit = fit_point_normals(
            &points,
            40,
            30,
            Point3::origin(),
            &PointNormalParams::default(),
        );
        let r = 5; // beyond the window's reach of the image border
        for v in r..30 - r {
            for u in r..40 - r {
                let i = v * 40 + u;
                assert!(fit.reliable[i], "({u}, {v}) unreliable");
                let err = angle_deg(fit.normals[i], n);
                assert!(err < 1e-3, "({u}, {v}): {err} deg");
            }
        }
    }

    #[test]
    fn a_sphere_gets_radial_normals_and_its_silhouette_is_unreliable() {
        // Sphere of radius 60 mm centred 400 mm in front of the camera.
        let (c, r) = (Vector3::new(0.0, 0.0, 400.0), 60.0);
        let depth = |x: f64, y: f64| {
            // Ray t (x, y, 1): |t d - c|^2 = r^2, nearest root.
            let d = Vector3::new(x, y, 1.0);
            let (a, b, k) = (d.dot(&d), -2.0 * d.dot(&c), c.dot(&c) - r * r);
            let disc = b * b - 4.0 * a * k;
            (disc >= 0.0).then(|| (-b - disc.sqrt()) / (2.0 * a))
        };
        let (w, h) = (80u32, 80u32);
        let points = point_map(w, h, 0.004, depth);
        let fit = fit_point_normals(
            &points,
            w,
            h,
            Point3::origin(),
            &PointNormalParams::default(),
        );
        let mut reliable_errors = Vec::new();
        let mut silhouette_unreliable = 0;
        let mut silhouette = 0;
        for (i, p) in points.iter().enumerate() {
            let Some(q) = surface_point(*p) else { continue };
            let radial = q.coords - c;
            let (u, v) = (i % w as usize, i / w as usize);
            let on_edge = [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)]
                .iter()
                .any(|(du, dv)| {
                    let (uu, vv) = (u as i64 + du, v as i64 + dv);
                    uu < 0
                        || vv < 0
                        || uu >= w as i64
                        || vv >= h as i64
                        || surface_point(points[(vv * w as i64 + uu) as usize]).is_none()
                });
            if on_edge {
                silhouette += 1;
                silhouette_unreliable += usize::from(!fit.reliable[i]);
            }
            if fit.reliable[i] {
                let facing = -radial.normalize().z; // 1 at the centre, 0 at the limb
                reliable_errors.push((facing, angle_deg(fit.normals[i], radial)));
            }
        }
        // Where the sphere faces the camera the window is symmetric about the pixel and the
        // plane's normal is the radius; towards the limb the points spread unevenly over the
        // window and the fit tilts a little.
        let worst = |min_facing: f64| {
            reliable_errors
                .iter()
                .filter(|(f, _)| *f >= min_facing)
                .map(|(_, e)| *e)
                .fold(0.0, f64::max)
        };
        // Measured: 0.17 deg within 26 deg of facing, 0.71 within 46, 2.2 at the limb.
        assert!(worst(0.9) < 0.3, "worst facing error {} deg", worst(0.9));
        assert!(
            worst(0.7) < 1.0,
            "worst error within 46 deg {} deg",
            worst(0.7)
        );
        assert!(worst(0.0) < 3.0, "worst error {} deg", worst(0.0));
        assert!(reliable_errors.len() > 2000, "{}", reliable_errors.len());
        assert_eq!(
            silhouette_unreliable, silhouette,
            "every silhouette pixel is unreliable"
        );
    }

    #[test]
    fn a_depth_step_is_unreliable_and_no_point_gets_no_normal() {
        // Two parallel planes 20 mm apart meeting at x = 0; a hole at the centre column.
        let depth = |x: f64, _y: f64| Some(if x < 0.0 { 500.0 } else { 520.0 });
        let mut points = point_map(40, 20, 0.002, depth);
        points[10 * 40 + 5] = [f32::NAN, 0.0, 0.0];
        let fit = fit_point_normals(
            &points,
            40,
            20,
            Point3::origin(),
            &PointNormalParams::default(),
        );
        for v in 5..15 {
            assert!(
                !fit.reliable[v * 40 + 20],
                "step at row {v} called reliable"
            );
            assert!(
                !fit.reliable[v * 40 + 19],
                "step at row {v} called reliable"
            );
            assert!(fit.reliable[v * 40 + 30], "flat part at row {v} unreliable");
        }
        assert_eq!(fit.normals[10 * 40 + 5], [0.0; 3]);
        assert!(!fit.reliable[10 * 40 + 5]);
    }
}
