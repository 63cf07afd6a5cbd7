//! The surface as the camera sees it, and the light/view geometry of the layer model.
//!
//! Conventions
//! - Images are camera-sized and row-major; pixel `(x, y)` has index `y * width + x`, centres at
//!   integer coordinates.
//! - Points are world-frame millimetres, normals unit vectors pointing out of the skin.
//! - `w_i` and `w_o` point from the surface to the light and to the camera.
//! - `t_i` is the tangential part of the refracted light direction divided by its normal part: it
//!   points away from the light and has length `tan(theta_t)`. Light entering at `x` reaches the layer
//!   at depth `z` at `x + z t_i`.
//! - `t_o` is the same for the view ray but points towards the camera: the camera pixel at `x_o`
//!   sees the layer at depth `z` at `x_o - z t_o`. A layer at depth `z` lit at `x` therefore shows up
//!   around `x + z (t_i + t_o)` (DESIGN section 5 writes `t_i - t_o` with `t_o` pointing away from
//!   the camera: the same thing).

use nalgebra::{Matrix2, Vector2, Vector3};

/// Which view-ray model to use for `t_o` (DESIGN section 5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ViewRay {
    /// Refracted at the surface with the tissue's index.
    Refracted,
    /// Unrefracted, as in paper eq. 5: `w_o / (w_o . N) - N`.
    Unrefracted,
    /// No view term (`t_o = 0`): the camera sees the light where it leaves the surface. Right
    /// for diffuse emergence, where the exit direction forgets the depth the light came from;
    /// the virtual booth's truth is exitance at the exit point (see `subsurface::layer_depth`).
    /// Default.
    #[default]
    ExitPoint,
}

/// Tangential offset per unit depth of a ray entering along `-w` (refracted with index `eta`),
/// pointing away from `w`; `None` when `w` is at or below the horizon.
pub fn refracted_tangent(
    w: &Vector3<f64>,
    normal: &Vector3<f64>,
    eta: f64,
) -> Option<Vector3<f64>> {
    let cos_i = w.dot(normal);
    if cos_i <= 1e-6 {
        return None;
    }
    let tangential = w - normal * cos_i;
    let sin_i = tangential.norm();
    if sin_i < 1e-12 {
        return Some(Vector3::zeros());
    }
    let sin_t = sin_i / eta;
    let cos_t = (1.0 - sin_t * sin_t).max(0.0).sqrt();
    Some(-tangential / sin_i * (sin_t / cos_t))
}

/// Unrefracted tangential offset per unit depth, pointing away from `w`.
pub fn straight_tangent(w: &Vector3<f64>, normal: &Vector3<f64>) -> Option<Vector3<f64>> {
    let cos_i = w.dot(normal);
    if cos_i <= 1e-6 {
        return None;
    }
    Some(-(w / cos_i - normal))
}

/// `t_i + t_o` for one surface point: where the layers' light moves per mm of depth.
pub fn shift_per_depth(
    point: &Vector3<f64>,
    normal: &Vector3<f64>,
    light: &Vector3<f64>,
    camera: &Vector3<f64>,
    eta: f64,
    view: ViewRay,
) -> Option<Vector3<f64>> {
    let w_i = (light - point).normalize();
    let w_o = (camera - point).normalize();
    let t_i = refracted_tangent(&w_i, normal, eta)?;
    // t_o points towards the camera: the negative of the "away" tangent of w_o.
    let t_o = match view {
        ViewRay::Refracted => -refracted_tangent(&w_o, normal, eta)?,
        ViewRay::Unrefracted => -straight_tangent(&w_o, normal)?,
        // The camera must still see the point (it is on the lit side of the surface).
        ViewRay::ExitPoint if w_o.dot(normal) <= 1e-6 => return None,
        ViewRay::ExitPoint => Vector3::zeros(),
    };
    Some(t_i + t_o)
}

/// The surface seen by the camera.
#[derive(Debug, Clone, PartialEq)]
pub struct Surface {
    pub width: usize,
    pub height: usize,
    /// World-frame point per pixel (mm); meaningless where `mask` is false.
    pub points: Vec<Vector3<f64>>,
    /// Unit normal per pixel.
    pub normals: Vec<Vector3<f64>>,
    /// Pixels on the subject.
    pub mask: Vec<bool>,
    /// Camera centre (world, mm).
    pub camera_centre: Vector3<f64>,
}

/// Local footprint of one pixel on the surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Footprint {
    /// `dP/dx` and `dP/dy` (mm per pixel).
    pub dx: Vector3<f64>,
    pub dy: Vector3<f64>,
}

impl Footprint {
    /// Surface area of the pixel (mm^2).
    pub fn area(&self) -> f64 {
        self.dx.cross(&self.dy).norm()
    }

    /// Smallest surface length (mm) a displacement of one pixel can have: the smaller singular
    /// value of `[dx dy]`, so a displacement of `d` mm is at most `d / stretch` pixels.
    pub fn smallest_stretch(&self) -> f64 {
        let (a, b, c) = (
            self.dx.dot(&self.dx),
            self.dx.dot(&self.dy),
            self.dy.dot(&self.dy),
        );
        let half_gap = (((a - c) / 2.0).powi(2) + b * b).sqrt();
        ((a + c) / 2.0 - half_gap).max(0.0).sqrt()
    }

    /// Pixel offset `(dx, dy)` whose surface displacement is closest to `d` (least squares).
    pub fn pixels_for(&self, d: &Vector3<f64>) -> Option<Vector2<f64>> {
        self.pixel_map().map(|m| m.pixels_for(d))
    }

    /// [`Footprint::pixels_for`] made ready for many displacements (the normal equations
    /// inverted once); `None` for a degenerate footprint.
    pub fn pixel_map(&self) -> Option<PixelMap> {
        let jtj = Matrix2::new(
            self.dx.dot(&self.dx),
            self.dx.dot(&self.dy),
            self.dy.dot(&self.dx),
            self.dy.dot(&self.dy),
        );
        jtj.try_inverse().map(|inverse| PixelMap {
            dx: self.dx,
            dy: self.dy,
            inverse,
        })
    }
}

/// A footprint's least-squares map from surface displacements to pixel offsets.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelMap {
    dx: Vector3<f64>,
    dy: Vector3<f64>,
    /// Inverse of the footprint's normal equations.
    inverse: Matrix2<f64>,
}

impl PixelMap {
    /// Pixel offset whose surface displacement is closest to `d` ([`Footprint::pixels_for`]).
    pub fn pixels_for(&self, d: &Vector3<f64>) -> Vector2<f64> {
        self.inverse * Vector2::new(self.dx.dot(d), self.dy.dot(d))
    }
}

impl Surface {
    /// The surface of rows `rows` alone (clamped to the image).
    pub fn rows(&self, rows: std::ops::Range<usize>) -> Self {
        let end = rows.end.min(self.height);
        let start = rows.start.min(end);
        let span = start * self.width..end * self.width;
        Self {
            width: self.width,
            height: end - start,
            points: self.points[span.clone()].to_vec(),
            normals: self.normals[span.clone()].to_vec(),
            mask: self.mask[span].to_vec(),
            camera_centre: self.camera_centre,
        }
    }

    /// The flat patch z = 0 on a `pitch` mm grid (pixel `(x, y)` at `(x, y) * pitch`), all of
    /// it skin, seen from `camera_centre`: the scene of the analytic tests.
    #[cfg(test)]
    pub(crate) fn flat(
        width: usize,
        height: usize,
        pitch: f64,
        camera_centre: Vector3<f64>,
    ) -> Self {
        let n = width * height;
        Self {
            width,
            height,
            points: (0..n)
                .map(|i| Vector3::new((i % width) as f64 * pitch, (i / width) as f64 * pitch, 0.0))
                .collect(),
            normals: vec![Vector3::z(); n],
            mask: vec![true; n],
            camera_centre,
        }
    }

    pub fn len(&self) -> usize {
        self.width * self.height
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Derivative of the surface point along one image axis at pixel `i`, from the neighbours on the
    /// subject (central difference, one-sided at the subject's edge).
    fn derivative(&self, i: usize, along_x: bool) -> Option<Vector3<f64>> {
        let (x, y) = (i % self.width, i / self.width);
        let neighbour = |forward: bool| -> Option<usize> {
            let (nx, ny) = match (along_x, forward) {
                (true, true) => (x + 1, y),
                (true, false) => (x.checked_sub(1)?, y),
                (false, true) => (x, y + 1),
                (false, false) => (x, y.checked_sub(1)?),
            };
            (nx < self.width && ny < self.height && self.mask[ny * self.width + nx])
                .then_some(ny * self.width + nx)
        };
        match (neighbour(false), neighbour(true)) {
            (Some(a), Some(b)) => Some((self.points[b] - self.points[a]) * 0.5),
            (None, Some(b)) => Some(self.points[b] - self.points[i]),
            (Some(a), None) => Some(self.points[i] - self.points[a]),
            (None, None) => None,
        }
    }

    /// Footprint of pixel `i`, `None` off the subject or where it has no neighbour along an axis.
    pub fn footprint(&self, i: usize) -> Option<Footprint> {
        if !self.mask[i] {
            return None;
        }
        let dx = self.derivative(i, true)?;
        let dy = self.derivative(i, false)?;
        let f = Footprint { dx, dy };
        (f.area() > 1e-12).then_some(f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refraction_obeys_snell_and_points_away_from_the_light() {
        let n = Vector3::z();
        let theta: f64 = 50f64.to_radians();
        // Light up and to the -x side: the refracted ray travels towards +x.
        let w = Vector3::new(-theta.sin(), 0.0, theta.cos());
        let t = refracted_tangent(&w, &n, 1.4).unwrap();
        let theta_t = (theta.sin() / 1.4).asin();
        assert!((t.x - theta_t.tan()).abs() < 1e-12 && t.y.abs() < 1e-15 && t.z.abs() < 1e-15);
        // Unrefracted: tan(theta) itself.
        let s = straight_tangent(&w, &n).unwrap();
        assert!((s.x - theta.tan()).abs() < 1e-12);
        // Grazing from below the horizon: no entry.
        assert!(refracted_tangent(&Vector3::new(1.0, 0.0, -0.1).normalize(), &n, 1.4).is_none());
    }

    #[test]
    fn light_and_camera_on_one_axis_give_no_shift() {
        let p = Vector3::new(1.0, 2.0, 0.0);
        let n = Vector3::z();
        let eye = Vector3::new(300.0, -100.0, 500.0);
        let s = shift_per_depth(&p, &n, &eye, &eye, 1.4, ViewRay::Refracted).unwrap();
        assert!(s.norm() < 1e-12);
        // Light at -x, camera overhead: the layers' light moves to +x.
        let s = shift_per_depth(
            &p,
            &n,
            &Vector3::new(-500.0, 2.0, 500.0),
            &Vector3::new(1.0, 2.0, 800.0),
            1.4,
            ViewRay::Refracted,
        )
        .unwrap();
        assert!(s.x > 0.5 && s.x < 0.6, "{s}"); // tan(asin(sin 45 / 1.4)) = 0.584
    }

    #[test]
    fn footprint_of_a_tilted_plane() {
        // z = 0.5 x on a 0.1 mm grid: dP/dx = (0.1, 0, 0.05).
        let (w, h) = (5, 4);
        let points = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64 * 0.1, (i / w) as f64 * 0.1);
                Vector3::new(x, y, 0.5 * x)
            })
            .collect();
        let s = Surface {
            width: w,
            height: h,
            points,
            normals: vec![Vector3::z(); w * h],
            mask: vec![true; w * h],
            camera_centre: Vector3::new(0.0, 0.0, 100.0),
        };
        for i in [0, 7, 19] {
            let f = s.footprint(i).unwrap();
            assert!((f.dx - Vector3::new(0.1, 0.0, 0.05)).norm() < 1e-12);
            assert!((f.area() - 0.1 * 0.1 * 1.25f64.sqrt()).abs() < 1e-12);
            let px = f.pixels_for(&Vector3::new(0.2, -0.1, 0.1)).unwrap();
            assert!((px - Vector2::new(2.0, -1.0)).norm() < 1e-9);
        }
    }
}
