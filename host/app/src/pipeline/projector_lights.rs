//! The booth's projectors as near point lights over the geometry stage's surface points, for the
//! stages that shade with them (`normals`, `separate`).
//!
//! Conventions
//! - World frame of the calibration, mm.
//! - Projector k at centre C_k with optical axis a_k lights a point X with irradiance
//!   `s_k cos(incidence) / (r^2 cos^3(alpha))`, r = |C_k - X|, alpha the angle between a_k and the
//!   ray: a projector's flat pixel grid puts more intensity off axis. `s_k = |C_k|^2` (the squared
//!   distance to the world origin, the subject's nominal centre) so that white at the origin
//!   facing the projector gets irradiance 1: the projectors are assumed equally bright.

use image::Rgb32FImage;
use nalgebra::{Point3, Vector3};

use mlsss_core::calibration::Calibration;
use mlsss_vision::photometry::photometric_stereo::{LightModel, LightSample};

/// Projectors as near point lights over a map of surface points.
pub struct ProjectorLights {
    pub centres: Vec<Point3<f64>>,
    /// Unit optical axes, world frame.
    pub axes: Vec<Vector3<f64>>,
    /// Intensity scale per projector (see the module conventions).
    pub scales: Vec<f64>,
    pub camera_centre: Point3<f64>,
    pub width: u32,
    /// World point per camera pixel; zero or non-finite where unknown.
    pub points: Vec<[f32; 3]>,
}

impl LightModel for ProjectorLights {
    fn count(&self) -> usize {
        self.centres.len()
    }

    fn at(&self, x: u32, y: u32, out: &mut [LightSample]) -> Option<Vector3<f64>> {
        let p = self.points.get((y * self.width + x) as usize)?;
        if p.iter().any(|v| !v.is_finite()) || p.iter().all(|v| *v == 0.0) {
            return None;
        }
        let point = Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        for (k, sample) in out.iter_mut().enumerate() {
            let to_light = self.centres[k] - point;
            let r2 = to_light.norm_squared();
            let direction = to_light / r2.sqrt();
            let cos_axis = (-direction).dot(&self.axes[k]);
            let irradiance = if cos_axis > 0.0 && r2 > 0.0 {
                self.scales[k] / (r2 * cos_axis.powi(3))
            } else {
                0.0
            };
            *sample = LightSample {
                direction,
                irradiance: [irradiance; 3],
            };
        }
        (self.camera_centre - point).try_normalize(1e-12)
    }
}

impl ProjectorLights {
    /// The first `count` projectors of `calib` lighting the surface `points` (a `width`-wide map).
    pub fn from_calibration(
        calib: &Calibration,
        count: usize,
        width: u32,
        points: &Rgb32FImage,
    ) -> Self {
        let projectors = &calib.projectors[..count];
        Self {
            centres: projectors
                .iter()
                .map(|p| p.device.extrinsics.centre())
                .collect(),
            axes: projectors
                .iter()
                .map(|p| p.device.extrinsics.device_to_world_dir(&Vector3::z()))
                .collect(),
            // See the module conventions: white at the origin facing a projector gets 1.
            scales: projectors
                .iter()
                .map(|p| p.device.extrinsics.centre().coords.norm_squared())
                .collect(),
            camera_centre: calib.camera.extrinsics.centre(),
            width,
            points: points.pixels().map(|p| p.0).collect(),
        }
    }
}
