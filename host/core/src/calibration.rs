//! Calibration model shared by every stage: pinhole intrinsics with OpenCV distortion, extrinsics,
//! and the calibration file (DESIGN section 8).
//!
//! Conventions
//! - World frame in millimetres. For the virtual booth it is the booth frame (`hardware/booth.toml`);
//!   for a real calibration it is the camera frame (camera R = I, t = 0).
//! - Extrinsics are OpenCV's: `x_device = R x_world + t`; the device looks along its +z axis,
//!   x right, y down.
//! - Pixel coordinates: origin at the top-left pixel, pixel centres at integer coordinates.
//! - Distortion is OpenCV's `[k1, k2, p1, p2, k3]`, applied to normalised coordinates.

use std::path::Path;

use nalgebra::{Matrix3, Point2, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Fixed-point iterations of [`Intrinsics::undistort`] at most.
const UNDISTORT_ITERATIONS: usize = 20;

/// Pinhole intrinsics plus OpenCV's 5-parameter distortion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// `[k1, k2, p1, p2, k3]`.
    pub distortion: [f64; 5],
}

impl Intrinsics {
    /// Applies the distortion model to normalised image coordinates.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        (xd, yd)
    }

    /// Inverts [`Intrinsics::distort`] by fixed-point iteration (converges for the moderate
    /// distortion of real lenses; 20 iterations reach well below 1e-9 for |k1| < 0.3).
    ///
    /// Stops as soon as an iteration leaves `(x, y)` bit for bit unchanged: the step is a
    /// function of `(x, y)` alone, so every later iteration would leave it unchanged too and the
    /// result is that of all 20 (bit-identical; `undistort_stops_only_at_an_exact_fixed_point`).
    /// Undistorted devices (the simulated projectors) then take one iteration instead of 20, a
    /// real lens about ten: the geometry stage casts five rays per camera pixel.
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..UNDISTORT_ITERATIONS {
            let (dx, dy) = self.distort(x, y);
            let (next_x, next_y) = (x + (xd - dx), y + (yd - dy));
            let fixed = next_x.to_bits() == x.to_bits() && next_y.to_bits() == y.to_bits();
            (x, y) = (next_x, next_y);
            if fixed {
                break;
            }
        }
        (x, y)
    }

    /// Pixel of a point given in the device frame, or `None` behind the device.
    pub fn project_device_point(&self, p: &Point3<f64>) -> Option<Point2<f64>> {
        if p.z <= 0.0 {
            return None;
        }
        let (xd, yd) = self.distort(p.x / p.z, p.y / p.z);
        Some(Point2::new(self.fx * xd + self.cx, self.fy * yd + self.cy))
    }

    /// Unit ray direction, in the device frame, through pixel `(u, v)`.
    pub fn pixel_ray(&self, u: f64, v: f64) -> Vector3<f64> {
        let (x, y) = self.undistort((u - self.cx) / self.fx, (v - self.cy) / self.fy);
        Vector3::new(x, y, 1.0).normalize()
    }

    /// The 3x3 camera matrix K.
    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }
}

/// Rigid pose of a device: `x_device = rotation * x_world + translation`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Extrinsics {
    /// Row-major 3x3 rotation, world to device.
    pub rotation: [[f64; 3]; 3],
    /// Translation in millimetres.
    pub translation: [f64; 3],
}

impl Extrinsics {
    /// The identity pose (device frame = world frame).
    pub fn identity() -> Self {
        Self::from_rt(&Matrix3::identity(), &Vector3::zeros())
    }

    /// A device at `position` looking at `target`, with image "up" (-y) closest to `up`.
    pub fn look_at(position: [f64; 3], target: [f64; 3], up: [f64; 3]) -> Self {
        let c = Vector3::from(position);
        let z = (Vector3::from(target) - c).normalize();
        // Image y points down, i.e. against `up`.
        let down = -Vector3::from(up);
        let x = down.cross(&z).normalize();
        let y = z.cross(&x);
        let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
        let t = -(r * c);
        Self::from_rt(&r, &t)
    }

    pub fn from_rt(r: &Matrix3<f64>, t: &Vector3<f64>) -> Self {
        let row = |i: usize| [r[(i, 0)], r[(i, 1)], r[(i, 2)]];
        Self {
            rotation: [row(0), row(1), row(2)],
            translation: [t.x, t.y, t.z],
        }
    }

    pub fn r(&self) -> Matrix3<f64> {
        let m = &self.rotation;
        Matrix3::new(
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
        )
    }

    pub fn t(&self) -> Vector3<f64> {
        Vector3::from(self.translation)
    }

    /// Position of the device's centre of projection in the world frame.
    pub fn centre(&self) -> Point3<f64> {
        Point3::from(-(self.r().transpose() * self.t()))
    }

    pub fn world_to_device(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.r() * p.coords + self.t())
    }

    pub fn device_to_world_dir(&self, d: &Vector3<f64>) -> Vector3<f64> {
        self.r().transpose() * d
    }
}

/// Calibration of one device (camera or projector).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DeviceCalibration {
    pub width: u32,
    pub height: u32,
    pub intrinsics: Intrinsics,
    pub extrinsics: Extrinsics,
}

impl DeviceCalibration {
    /// Pixel where a world point lands, or `None` behind the device.
    pub fn project(&self, world: &Point3<f64>) -> Option<Point2<f64>> {
        self.intrinsics
            .project_device_point(&self.extrinsics.world_to_device(world))
    }

    /// World-frame ray (origin, unit direction) through pixel `(u, v)`.
    pub fn ray(&self, u: f64, v: f64) -> (Point3<f64>, Vector3<f64>) {
        let d = self.intrinsics.pixel_ray(u, v);
        (
            self.extrinsics.centre(),
            self.extrinsics.device_to_world_dir(&d),
        )
    }
}

/// Photometric response of a projector: emitted = black + (1 - black) * value^gamma.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProjectorResponse {
    pub gamma: f64,
    pub black_level: f64,
}

/// One projector's entry in the calibration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProjectorCalibration {
    #[serde(flatten)]
    pub device: DeviceCalibration,
    /// Response curve, when a photometric calibration was made.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub response: Option<ProjectorResponse>,
    /// RMS reprojection error of this projector's correspondences, in projector pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rms_px: Option<f64>,
}

/// The calibration file: camera and projectors in one world frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    pub camera: DeviceCalibration,
    /// RMS reprojection error of the camera, in camera pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_rms_px: Option<f64>,
    pub projectors: Vec<ProjectorCalibration>,
}

/// Errors reading or writing a calibration file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CalibrationError {
    /// The file could not be read or written.
    #[error("calibration file {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    /// The file is not a valid calibration JSON.
    #[error("calibration file {path} is not valid: {source}")]
    Json {
        path: String,
        source: serde_json::Error,
    },
    /// A value of the calibration is out of range (a zero or non-finite focal length, ...).
    #[error("calibration file {path}: `{field}`: {reason}")]
    Invalid {
        path: String,
        field: String,
        reason: String,
    },
}

impl DeviceCalibration {
    /// The field (below the device) and reason of the first value out of range: image size
    /// positive, focal lengths finite and positive, every other number finite.
    fn invalid_value(&self) -> Option<(&'static str, String)> {
        if self.width == 0 || self.height == 0 {
            return Some(("width/height", "must be positive".into()));
        }
        let k = &self.intrinsics;
        if !(k.fx > 0.0 && k.fy > 0.0 && k.fx.is_finite() && k.fy.is_finite()) {
            return Some((
                "intrinsics.fx/fy",
                format!("must be finite and positive, got {} and {}", k.fx, k.fy),
            ));
        }
        let finite = |values: &[f64]| values.iter().all(|v| v.is_finite());
        if !finite(&[k.cx, k.cy]) || !finite(&k.distortion) {
            return Some(("intrinsics", "every value must be finite".into()));
        }
        let e = &self.extrinsics;
        if !finite(e.rotation.as_flattened()) || !finite(&e.translation) {
            return Some(("extrinsics", "every value must be finite".into()));
        }
        None
    }
}

impl Calibration {
    pub fn load(path: &Path) -> Result<Self, CalibrationError> {
        let text = std::fs::read_to_string(path).map_err(|source| CalibrationError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let calibration: Self =
            serde_json::from_str(&text).map_err(|source| CalibrationError::Json {
                path: path.display().to_string(),
                source,
            })?;
        calibration.validate(path)?;
        Ok(calibration)
    }

    /// Checks every device's values ([`CalibrationError::Invalid`] names the device and field).
    pub fn validate(&self, path: &Path) -> Result<(), CalibrationError> {
        let devices = std::iter::once(("camera".to_owned(), &self.camera)).chain(
            self.projectors
                .iter()
                .enumerate()
                .map(|(k, p)| (format!("projectors[{k}]"), &p.device)),
        );
        for (name, device) in devices {
            if let Some((field, reason)) = device.invalid_value() {
                return Err(CalibrationError::Invalid {
                    path: path.display().to_string(),
                    field: format!("{name}.{field}"),
                    reason,
                });
            }
        }
        Ok(())
    }

    pub fn save(&self, path: &Path) -> Result<(), CalibrationError> {
        let text = serde_json::to_string_pretty(self).map_err(|source| CalibrationError::Json {
            path: path.display().to_string(),
            source,
        })?;
        crate::atomic_file::write_bytes_atomically(path, text.as_bytes()).map_err(|source| {
            CalibrationError::Io {
                path: path.display().to_string(),
                source,
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn look_at_puts_target_on_optical_axis_and_up_is_up() {
        let e = Extrinsics::look_at([100.0, -50.0, -400.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0]);
        let target = e.world_to_device(&Point3::origin());
        assert_relative_eq!(target.x, 0.0, epsilon = 1e-9);
        assert_relative_eq!(target.y, 0.0, epsilon = 1e-9);
        assert!(target.z > 0.0);
        // A point above the target (world -y) appears higher in the image (device -y).
        let above = e.world_to_device(&Point3::new(0.0, -10.0, 0.0));
        assert!(above.y < 0.0);
        assert_relative_eq!(
            e.centre(),
            Point3::new(100.0, -50.0, -400.0),
            epsilon = 1e-9
        );
    }

    #[test]
    fn a_calibration_with_a_zero_focal_length_is_refused_on_load() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("calib.json");
        let mut calibration = crate::booth::Booth::builtin(true).calibration();
        calibration.save(&path).unwrap();
        Calibration::load(&path).expect("the booth's own calibration is valid");
        calibration.projectors[2].device.intrinsics.fx = 0.0;
        calibration.save(&path).unwrap();
        let err = Calibration::load(&path).unwrap_err();
        assert!(
            err.to_string().contains("projectors[2].intrinsics.fx/fy"),
            "{err}"
        );
    }

    /// The plain inverse: all 20 fixed-point iterations, as before the early stop.
    fn undistort_all_iterations(k: &Intrinsics, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..UNDISTORT_ITERATIONS {
            let (dx, dy) = k.distort(x, y);
            x += xd - dx;
            y += yd - dy;
        }
        (x, y)
    }

    proptest::proptest! {
        /// The early stop returns the bits of the full 20 iterations, for real-lens
        /// distortions, none at all, and points out to the corners of a wide lens.
        #[test]
        fn undistort_stops_only_at_an_exact_fixed_point(
            k1 in -0.3f64..0.3, k2 in -0.1f64..0.1, p1 in -0.003f64..0.003,
            p2 in -0.003f64..0.003, k3 in -0.02f64..0.02, zero in proptest::bool::ANY,
            xd in -0.6f64..0.6, yd in -0.45f64..0.45,
        ) {
            let k = Intrinsics {
                fx: 1000.0,
                fy: 1000.0,
                cx: 320.0,
                cy: 240.0,
                distortion: if zero { [0.0; 5] } else { [k1, k2, p1, p2, k3] },
            };
            let (x, y) = k.undistort(xd, yd);
            let (xa, ya) = undistort_all_iterations(&k, xd, yd);
            proptest::prop_assert_eq!((x.to_bits(), y.to_bits()), (xa.to_bits(), ya.to_bits()));
        }
    }

    #[test]
    fn undistort_keeps_non_finite_and_signed_zero_inputs_as_before() {
        let k = Intrinsics {
            fx: 1000.0,
            fy: 1000.0,
            cx: 320.0,
            cy: 240.0,
            distortion: [-0.08, 0.05, 0.0, 0.0, 0.0],
        };
        for &(xd, yd) in &[
            (-0.0, 0.0),
            (f64::NAN, 0.1),
            (f64::INFINITY, -0.2),
            (1e300, 1.0),
        ] {
            let (x, y) = k.undistort(xd, yd);
            let (xa, ya) = undistort_all_iterations(&k, xd, yd);
            assert_eq!((x.to_bits(), y.to_bits()), (xa.to_bits(), ya.to_bits()));
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        let k = Intrinsics {
            fx: 1000.0,
            fy: 1000.0,
            cx: 320.0,
            cy: 240.0,
            distortion: [-0.2, 0.08, 0.001, -0.002, 0.01],
        };
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.4, 0.35)] {
            let (xd, yd) = k.distort(x, y);
            let (xu, yu) = k.undistort(xd, yd);
            assert_relative_eq!(xu, x, epsilon = 1e-10);
            assert_relative_eq!(yu, y, epsilon = 1e-10);
        }
    }
}
