//! Errors of an estimated calibration against the simulator's true one.
//!
//! Conventions
//! - A calibration from chessboard poses has its own world frame (the camera's, see
//!   `calibrate::procam`); the truth has the booth's. The world frame is a free choice (a gauge),
//!   so before any comparison the estimate is re-expressed in the truth's world frame through the
//!   TRUE camera pose ([`align_world_frame`]). Every relative quantity the calibration measured
//!   (intrinsics, projector poses relative to the camera) is unchanged by this.
//! - Focal lengths compare as relative errors in percent, principal points as pixel offsets and
//!   as percent of the image size, centres of projection as millimetres, orientations as the
//!   angle of the relative rotation in degrees.

use nalgebra::Matrix3;
use serde::{Deserialize, Serialize};

use mlsss_core::calibration::{Calibration, DeviceCalibration, Extrinsics};

/// Errors of the comparison.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum CalibrationErrorError {
    /// The estimate and the truth do not describe the same number of projectors.
    #[error("the estimate has {estimated} projectors, the truth {truth}")]
    ProjectorCount { estimated: usize, truth: usize },
}

/// Errors of one device.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DeviceErrors {
    /// `(f_est - f_true) / f_true`, percent, per axis.
    pub fx_rel_pct: f64,
    pub fy_rel_pct: f64,
    /// `c_est - c_true`, pixels.
    pub cx_px: f64,
    pub cy_px: f64,
    /// Principal point offsets as percent of the image width / height.
    pub cx_pct_of_width: f64,
    pub cy_pct_of_height: f64,
    /// Distance between the estimated and true centres of projection, mm (0 for the camera,
    /// whose pose defines the aligned frame).
    pub centre_mm: f64,
    /// Angle of `R_est R_true^T`, degrees.
    pub rotation_deg: f64,
}

/// Errors of a whole calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationErrors {
    pub camera: DeviceErrors,
    pub projectors: Vec<DeviceErrors>,
    /// Largest |focal error| over every device, percent.
    pub max_focal_rel_pct: f64,
    /// Largest principal point offset over every device, pixels.
    pub max_principal_point_px: f64,
    /// Largest projector centre error, mm.
    pub max_projector_centre_mm: f64,
    /// Largest projector orientation error, degrees.
    pub max_projector_rotation_deg: f64,
}

/// `estimate` with its world frame replaced by the frame in which its camera has `camera_pose`.
pub fn align_world_frame(estimate: &Calibration, camera_pose: &Extrinsics) -> Calibration {
    // Each pose maps the estimate's world W_est to its device. Compose it with the map from the
    // new world to W_est: W_new -> camera (`camera_pose`), then camera -> W_est (the inverse of
    // the estimate's own camera pose).
    let cam_est = &estimate.camera.extrinsics;
    let (rc, tc) = (cam_est.r(), cam_est.t());
    let (rn, tn) = (camera_pose.r(), camera_pose.t());
    // W_new -> W_est: x_est = rc^T (rn x + tn - tc).
    let r_map = rc.transpose() * rn;
    let t_map = rc.transpose() * (tn - tc);
    let rebase = |e: &Extrinsics| {
        let (r, t) = (e.r(), e.t());
        Extrinsics::from_rt(&(r * r_map), &(r * t_map + t))
    };
    let mut out = estimate.clone();
    out.camera.extrinsics = rebase(&estimate.camera.extrinsics);
    for p in &mut out.projectors {
        p.device.extrinsics = rebase(&p.device.extrinsics);
    }
    out
}

fn rotation_angle_deg(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    let rel = a * b.transpose();
    let cos = ((rel.trace() - 1.0) / 2.0).clamp(-1.0, 1.0);
    cos.acos().to_degrees()
}

fn device_errors(est: &DeviceCalibration, truth: &DeviceCalibration) -> DeviceErrors {
    let (e, t) = (&est.intrinsics, &truth.intrinsics);
    let centre = est.extrinsics.centre() - truth.extrinsics.centre();
    DeviceErrors {
        fx_rel_pct: 100.0 * (e.fx - t.fx) / t.fx,
        fy_rel_pct: 100.0 * (e.fy - t.fy) / t.fy,
        cx_px: e.cx - t.cx,
        cy_px: e.cy - t.cy,
        cx_pct_of_width: 100.0 * (e.cx - t.cx) / f64::from(truth.width.max(1)),
        cy_pct_of_height: 100.0 * (e.cy - t.cy) / f64::from(truth.height.max(1)),
        centre_mm: centre.norm(),
        rotation_deg: rotation_angle_deg(&est.extrinsics.r(), &truth.extrinsics.r()),
    }
}

/// Compares `estimate` (in any world frame) with `truth`.
pub fn calibration_errors(
    estimate: &Calibration,
    truth: &Calibration,
) -> Result<CalibrationErrors, CalibrationErrorError> {
    if estimate.projectors.len() != truth.projectors.len() {
        return Err(CalibrationErrorError::ProjectorCount {
            estimated: estimate.projectors.len(),
            truth: truth.projectors.len(),
        });
    }
    let aligned = align_world_frame(estimate, &truth.camera.extrinsics);
    let camera = device_errors(&aligned.camera, &truth.camera);
    let projectors: Vec<DeviceErrors> = aligned
        .projectors
        .iter()
        .zip(&truth.projectors)
        .map(|(e, t)| device_errors(&e.device, &t.device))
        .collect();
    let all = || std::iter::once(&camera).chain(&projectors);
    let max = |it: &mut dyn Iterator<Item = f64>| it.fold(0.0f64, f64::max);
    Ok(CalibrationErrors {
        max_focal_rel_pct: max(&mut all().flat_map(|d| [d.fx_rel_pct.abs(), d.fy_rel_pct.abs()])),
        max_principal_point_px: max(&mut all().map(|d| d.cx_px.hypot(d.cy_px))),
        max_projector_centre_mm: max(&mut projectors.iter().map(|d| d.centre_mm)),
        max_projector_rotation_deg: max(&mut projectors.iter().map(|d| d.rotation_deg)),
        camera,
        projectors,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use mlsss_core::booth::Booth;
    use nalgebra::{Point3, Rotation3, Vector3};

    /// The truth expressed in its camera's frame (what `calibrate_procam` returns).
    fn in_camera_frame(truth: &Calibration) -> Calibration {
        align_world_frame(truth, &Extrinsics::identity())
    }

    #[test]
    fn the_truth_in_its_camera_frame_has_no_error() {
        let truth = Booth::builtin(true).calibration();
        let est = in_camera_frame(&truth);
        assert_relative_eq!(
            est.camera.extrinsics.r(),
            Matrix3::identity(),
            epsilon = 1e-9
        );
        let e = calibration_errors(&est, &truth).unwrap();
        assert!(e.max_projector_centre_mm < 1e-9, "{e:?}");
        assert!(e.max_projector_rotation_deg < 1e-5, "{e:?}");
        assert!(e.max_focal_rel_pct < 1e-12 && e.max_principal_point_px < 1e-12);
        // The aligned estimate projects world points exactly as the truth does.
        let aligned = align_world_frame(&est, &truth.camera.extrinsics);
        let p = Point3::new(3.0, -7.0, 12.0);
        let (a, b) = (
            aligned.projectors[2].device.project(&p).unwrap(),
            truth.projectors[2].device.project(&p).unwrap(),
        );
        assert_relative_eq!(a, b, epsilon = 1e-9);
    }

    #[test]
    fn known_perturbations_are_reported_exactly() {
        let truth = Booth::builtin(true).calibration();
        let mut est = in_camera_frame(&truth);
        est.camera.intrinsics.fx *= 1.01;
        est.camera.intrinsics.cy += 3.0;
        // Projector 1 moved 2 mm along the camera's x axis and turned 0.5 degrees about y.
        let p = &mut est.projectors[1].device.extrinsics;
        let turn = Rotation3::from_axis_angle(&Vector3::y_axis(), 0.5f64.to_radians());
        let centre = p.centre().coords + Vector3::new(2.0, 0.0, 0.0);
        let r = p.r() * turn.matrix();
        *p = Extrinsics::from_rt(&r, &(-(r * centre)));
        let e = calibration_errors(&est, &truth).unwrap();
        assert_relative_eq!(e.camera.fx_rel_pct, 1.0, epsilon = 1e-9);
        assert_relative_eq!(e.camera.cy_px, 3.0, epsilon = 1e-9);
        assert_relative_eq!(e.projectors[1].centre_mm, 2.0, epsilon = 1e-6);
        assert_relative_eq!(e.projectors[1].rotation_deg, 0.5, epsilon = 1e-6);
        assert!(e.projectors[0].centre_mm < 1e-9);
        assert_relative_eq!(e.max_projector_centre_mm, 2.0, epsilon = 1e-6);
        assert_relative_eq!(e.max_focal_rel_pct, 1.0, epsilon = 1e-9);
        est.projectors.pop();
        assert!(calibration_errors(&est, &truth).is_err());
    }
}
