//! The subjects the virtual booth can image: a skin plane, a skin sphere, a head, and a planar
//! chessboard target for calibration captures. Each answers ray queries (camera rays and shadow
//! rays towards the projectors).
//!
//! Conventions
//! - World frame of the booth (mm, x right, y down, z away from the camera); the subject sits
//!   around the origin, facing the camera (towards -z).
//! - Normals are unit vectors pointing out of the subject.
//! - Chessboard: board frame X right along the rows of corners, Y down, Z into the board; inner
//!   corner (i, j) is at (i s, j s, 0) as in OpenCV's object points; world = R X + t.

use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use serde::Serialize;

use super::head::Head;

/// Which subject to simulate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum SubjectKind {
    /// A flat patch of skin filling the view, facing the camera at z = 0.
    Plane,
    /// A sphere of skin touching z = 0.
    Sphere,
    /// A face: forehead, nose, cheeks.
    Head,
    /// A printed chessboard (calibration target).
    Chessboard,
}

/// A ray hit: distance along the ray, point and outward normal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub t: f64,
    pub point: Point3<f64>,
    pub normal: Vector3<f64>,
}

/// A planar chessboard target in one pose.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Chessboard {
    /// Inner corners along X and Y (OpenCV's pattern size).
    pub inner_corners: [u32; 2],
    pub square_mm: f64,
    /// White margin around the outer squares, mm.
    pub margin_mm: f64,
    /// Board-to-world rotation (row-major) and translation (mm).
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
    /// Diffuse albedo of the white and black squares (matte print).
    pub albedo_white: f64,
    pub albedo_black: f64,
}

impl Chessboard {
    fn r(&self) -> Matrix3<f64> {
        let m = &self.rotation;
        Matrix3::new(
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
        )
    }

    /// A board centred near the origin, tilted by `tilt_x`/`tilt_y` and rolled by `roll`
    /// (degrees), shifted by `offset` (mm).
    pub fn posed(
        inner_corners: [u32; 2],
        square_mm: f64,
        tilt_x_deg: f64,
        tilt_y_deg: f64,
        roll_deg: f64,
        offset: [f64; 3],
    ) -> Self {
        let r = Rotation3::from_euler_angles(
            tilt_x_deg.to_radians(),
            tilt_y_deg.to_radians(),
            roll_deg.to_radians(),
        )
        .into_inner();
        // Centre of the inner-corner grid in the board frame goes to `offset`.
        let centre = Vector3::new(
            0.5 * (inner_corners[0] - 1) as f64 * square_mm,
            0.5 * (inner_corners[1] - 1) as f64 * square_mm,
            0.0,
        );
        let t = Vector3::from(offset) - r * centre;
        let row = |i: usize| [r[(i, 0)], r[(i, 1)], r[(i, 2)]];
        Self {
            inner_corners,
            square_mm,
            margin_mm: 0.6 * square_mm,
            rotation: [row(0), row(1), row(2)],
            translation: [t.x, t.y, t.z],
            albedo_white: 0.8,
            albedo_black: 0.04,
        }
    }

    /// World positions of the inner corners, row by row (OpenCV order).
    pub fn inner_corner_points(&self) -> Vec<Point3<f64>> {
        let r = self.r();
        let t = Vector3::from(self.translation);
        let [nx, ny] = self.inner_corners;
        (0..ny)
            .flat_map(|j| (0..nx).map(move |i| (i, j)))
            .map(|(i, j)| {
                let board = Vector3::new(i as f64 * self.square_mm, j as f64 * self.square_mm, 0.0);
                Point3::from(r * board + t)
            })
            .collect()
    }

    fn normal(&self) -> Vector3<f64> {
        // Board +Z points into the board; the printed face looks along -Z.
        -(self.r() * Vector3::z())
    }

    fn intersect(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<Hit> {
        let r = self.r();
        let t0 = Vector3::from(self.translation);
        let o_b = r.transpose() * (origin.coords - t0);
        let d_b = r.transpose() * dir;
        if d_b.z.abs() < 1e-12 {
            return None;
        }
        let t = -o_b.z / d_b.z;
        if t <= 1e-9 {
            return None;
        }
        let p_b = o_b + d_b * t;
        self.on_board(p_b.x, p_b.y).then(|| Hit {
            t,
            point: origin + dir * t,
            normal: self.normal(),
        })
    }

    fn on_board(&self, x: f64, y: f64) -> bool {
        let s = self.square_mm;
        let lo = -s - self.margin_mm;
        let hi_x = self.inner_corners[0] as f64 * s + self.margin_mm;
        let hi_y = self.inner_corners[1] as f64 * s + self.margin_mm;
        (lo..hi_x).contains(&x) && (lo..hi_y).contains(&y)
    }

    /// Diffuse albedo at a world point on the board.
    pub fn albedo(&self, p: &Point3<f64>) -> f64 {
        let r = self.r();
        let b = r.transpose() * (p.coords - Vector3::from(self.translation));
        let s = self.square_mm;
        let (i, j) = ((b.x / s).floor(), (b.y / s).floor());
        let inside = i >= -1.0
            && j >= -1.0
            && i <= self.inner_corners[0] as f64 - 1.0
            && j <= self.inner_corners[1] as f64 - 1.0;
        // The corner square (-1, -1) is black, like OpenCV's printed pattern.
        if inside && (i + j).rem_euclid(2.0) == 0.0 {
            self.albedo_black
        } else {
            self.albedo_white
        }
    }
}

/// A subject placed in the booth.
#[derive(Debug, Clone)]
pub enum Subject {
    /// Skin plane z = 0.
    Plane,
    /// Skin sphere centred at (0, 0, radius).
    Sphere {
        radius_mm: f64,
    },
    Head(Head),
    Chessboard(Chessboard),
}

impl Subject {
    /// Does the subject's surface scatter light below the surface (skin) or only at it (paper)?
    pub fn is_skin(&self) -> bool {
        !matches!(self, Subject::Chessboard(_))
    }

    /// First hit of the ray `origin + t dir`, `t` in `(t_min, t_max)`; `dir` is a unit vector.
    pub fn intersect(
        &self,
        origin: &Point3<f64>,
        dir: &Vector3<f64>,
        t_min: f64,
        t_max: f64,
    ) -> Option<Hit> {
        let hit = match self {
            Subject::Plane => {
                if dir.z.abs() < 1e-12 {
                    return None;
                }
                let t = -origin.z / dir.z;
                Some(Hit {
                    t,
                    point: origin + dir * t,
                    normal: -Vector3::z(),
                })
            }
            Subject::Sphere { radius_mm } => sphere_hit(origin, dir, *radius_mm, t_min),
            Subject::Head(head) => head.intersect(origin, dir, t_min, t_max).map(|t| {
                let point = origin + dir * t;
                Hit {
                    t,
                    point,
                    normal: head.normal(point.x, point.y),
                }
            }),
            Subject::Chessboard(board) => board.intersect(origin, dir),
        }?;
        (hit.t > t_min && hit.t < t_max).then_some(hit)
    }

    /// Is the segment from surface point `p` (outward normal `n`) to `light` blocked?
    pub fn shadowed(&self, p: &Point3<f64>, n: &Vector3<f64>, light: &Point3<f64>) -> bool {
        // Only the head is non-convex; planes, spheres and boards cannot shadow themselves
        // on their lit side.
        let Subject::Head(_) = self else {
            return false;
        };
        let start = p + n * 0.02;
        let to_light = light - start;
        let dist = to_light.norm();
        self.intersect(&start, &(to_light / dist), 1e-6, dist)
            .is_some()
    }
}

fn sphere_hit(origin: &Point3<f64>, dir: &Vector3<f64>, radius: f64, t_min: f64) -> Option<Hit> {
    let centre = Point3::new(0.0, 0.0, radius);
    let oc = origin - centre;
    let b = oc.dot(dir);
    let c = oc.norm_squared() - radius * radius;
    let disc = b * b - c;
    if disc < 0.0 {
        return None;
    }
    let sq = disc.sqrt();
    let t = if -b - sq > t_min { -b - sq } else { -b + sq };
    let point = origin + dir * t;
    Some(Hit {
        t,
        point,
        normal: (point - centre) / radius,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_normal_is_radial_and_faces_the_ray() {
        let s = Subject::Sphere { radius_mm: 30.0 };
        let o = Point3::new(5.0, -3.0, -500.0);
        let hit = s.intersect(&o, &Vector3::z(), 0.0, 1e4).unwrap();
        assert!((hit.point - Point3::new(0.0, 0.0, 30.0)).norm() - 30.0 < 1e-9);
        assert!(hit.normal.dot(&Vector3::z()) < 0.0);
    }

    #[test]
    fn chessboard_corners_lie_on_square_boundaries() {
        let b = Chessboard::posed([9, 7], 8.0, 10.0, -15.0, 5.0, [1.0, 2.0, 3.0]);
        let corners = b.inner_corner_points();
        assert_eq!(corners.len(), 63);
        // Adjacent corners are one square apart; the grid centre is at the offset.
        assert!(((corners[1] - corners[0]).norm() - 8.0).abs() < 1e-9);
        let centre = corners[31];
        assert!((centre - Point3::new(1.0, 2.0, 3.0)).norm() < 1e-9);
        // The four squares around a corner alternate in colour.
        let n = b.normal();
        let r = b.r();
        let at =
            |dx: f64, dy: f64| b.albedo(&(corners[10] + r * Vector3::new(dx, dy, 0.0) + n * 0.0));
        assert_ne!(at(1.0, 1.0), at(-1.0, 1.0));
        assert_eq!(at(1.0, 1.0), at(-1.0, -1.0));
    }
}
