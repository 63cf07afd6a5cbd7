//! Bundle adjustment of a rig of pinhole devices (one camera, any number of projectors treated as
//! inverse cameras) observing a planar board in several views: intrinsics with OpenCV distortion,
//! device poses relative to the reference device, and one board pose per view, refined together by
//! Levenberg-Marquardt on the reprojection error.
//!
//! Conventions
//! - Device 0 is the reference (the camera); the rig frame is its frame.
//! - Board points are in millimetres on the board plane z = 0.
//! - `view_poses[j]`: board -> reference, `x_ref = R x_board + t`.
//! - `device_poses[d]`: reference -> device d, `x_d = R x_ref + t` (identity for device 0).
//! - Rotations are parametrised by rotation vectors (axis times angle, Rodrigues, as OpenCV).
//! - Pixel coordinates as in [`mlsss_core::calibration`]: origin at the top-left pixel centre.

use nalgebra::{DVector, Point3, Rotation3, Vector2, Vector3};

use super::levenberg_marquardt::{self, LmError, LmOptions, minimise};
use mlsss_core::calibration::Intrinsics;

/// Why a bundle adjustment failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum BundleAdjustmentError {
    /// An observation names a device or view the model does not have.
    #[error(
        "observation refers to device {device} / view {view}, the model has {devices} devices and {views} views"
    )]
    BadIndex {
        device: usize,
        view: usize,
        devices: usize,
        views: usize,
    },
    /// The optimiser could not run.
    #[error(transparent)]
    Optimiser(#[from] LmError),
}

/// A rigid transform `x' = R x + t` with `R` as a rotation vector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub rotation: Vector3<f64>,
    pub translation: Vector3<f64>,
}

impl Pose {
    pub fn identity() -> Self {
        Self {
            rotation: Vector3::zeros(),
            translation: Vector3::zeros(),
        }
    }

    pub fn from_rotation(r: &Rotation3<f64>, t: Vector3<f64>) -> Self {
        Self {
            rotation: r.scaled_axis(),
            translation: t,
        }
    }

    pub fn rotation_matrix(&self) -> Rotation3<f64> {
        Rotation3::from_scaled_axis(self.rotation)
    }

    pub fn apply(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation_matrix() * p + self.translation
    }

    /// `self` after `first`: `x -> self(first(x))`.
    pub fn compose(&self, first: &Pose) -> Pose {
        let r = self.rotation_matrix() * first.rotation_matrix();
        Pose::from_rotation(
            &r,
            self.rotation_matrix() * first.translation + self.translation,
        )
    }

    pub fn inverse(&self) -> Pose {
        let r_inv = self.rotation_matrix().inverse();
        Pose::from_rotation(&r_inv, -(r_inv * self.translation))
    }
}

/// One measured board corner: `device` saw board point `board` at `pixel` in view `view`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    pub device: usize,
    pub view: usize,
    pub board: Vector3<f64>,
    pub pixel: Vector2<f64>,
}

/// Parameters of the rig.
#[derive(Debug, Clone, PartialEq)]
pub struct RigModel {
    pub intrinsics: Vec<Intrinsics>,
    /// Reference -> device; entry 0 is the identity and is never changed.
    pub device_poses: Vec<Pose>,
    /// Board -> reference, one per view.
    pub view_poses: Vec<Pose>,
}

/// Which intrinsic parameters are refined.
#[derive(Debug, Clone, PartialEq)]
pub struct RefineOptions {
    /// Refine `[k1, k2, p1, p2, k3]` element by element.
    pub distortion: [bool; 5],
    /// Per device (in model order), which distortion terms are refined; when given it replaces
    /// `distortion` (a term not refined keeps its value in the model).
    pub device_distortion: Option<Vec<[bool; 5]>>,
    /// Refine focal lengths and principal points.
    pub pinhole: bool,
    pub lm: LmOptions,
}

impl Default for RefineOptions {
    fn default() -> Self {
        Self {
            distortion: [true; 5],
            device_distortion: None,
            pinhole: true,
            lm: LmOptions::default(),
        }
    }
}

const INTRINSIC_PARAMS: usize = 9;
const POSE_PARAMS: usize = 6;

impl RigModel {
    fn devices(&self) -> usize {
        self.intrinsics.len()
    }

    fn to_vector(&self) -> DVector<f64> {
        let mut v = Vec::new();
        for k in &self.intrinsics {
            v.extend_from_slice(&[k.fx, k.fy, k.cx, k.cy]);
            v.extend_from_slice(&k.distortion);
        }
        for pose in self.device_poses.iter().skip(1).chain(&self.view_poses) {
            v.extend(pose.rotation.iter());
            v.extend(pose.translation.iter());
        }
        DVector::from_vec(v)
    }

    fn with_vector(&self, v: &DVector<f64>) -> RigModel {
        let mut out = self.clone();
        for (d, k) in out.intrinsics.iter_mut().enumerate() {
            let s = &v.as_slice()[d * INTRINSIC_PARAMS..(d + 1) * INTRINSIC_PARAMS];
            *k = Intrinsics {
                fx: s[0],
                fy: s[1],
                cx: s[2],
                cy: s[3],
                distortion: [s[4], s[5], s[6], s[7], s[8]],
            };
        }
        let mut offset = self.devices() * INTRINSIC_PARAMS;
        let poses = out
            .device_poses
            .iter_mut()
            .skip(1)
            .chain(out.view_poses.iter_mut());
        for pose in poses {
            let s = &v.as_slice()[offset..offset + POSE_PARAMS];
            pose.rotation = Vector3::new(s[0], s[1], s[2]);
            pose.translation = Vector3::new(s[3], s[4], s[5]);
            offset += POSE_PARAMS;
        }
        out
    }

    /// Pixel where device `device` sees board point `board` of view `view` (`None` behind it).
    pub fn project(
        &self,
        device: usize,
        view: usize,
        board: &Vector3<f64>,
    ) -> Option<Vector2<f64>> {
        let x_ref = self.view_poses[view].apply(board);
        let x_dev = self.device_poses[device].apply(&x_ref);
        self.intrinsics[device]
            .project_device_point(&Point3::from(x_dev))
            .map(|p| p.coords)
    }

    /// Reprojection residual (predicted minus measured, pixels) of each observation; `None` when
    /// the point falls behind the device.
    pub fn residuals(&self, observations: &[Observation]) -> Vec<Option<Vector2<f64>>> {
        // Rotation matrices once per evaluation, not once per observation.
        let views: Vec<(Rotation3<f64>, Vector3<f64>)> = self
            .view_poses
            .iter()
            .map(|p| (p.rotation_matrix(), p.translation))
            .collect();
        let devices: Vec<(Rotation3<f64>, Vector3<f64>)> = self
            .device_poses
            .iter()
            .map(|p| (p.rotation_matrix(), p.translation))
            .collect();
        observations
            .iter()
            .map(|o| {
                let (rv, tv) = &views[o.view];
                let (rd, td) = &devices[o.device];
                let x = rd * (rv * o.board + tv) + td;
                self.intrinsics[o.device]
                    .project_device_point(&Point3::from(x))
                    .map(|p| p.coords - o.pixel)
            })
            .collect()
    }

    fn check(&self, observations: &[Observation]) -> Result<(), BundleAdjustmentError> {
        for o in observations {
            if o.device >= self.devices() || o.view >= self.view_poses.len() {
                return Err(BundleAdjustmentError::BadIndex {
                    device: o.device,
                    view: o.view,
                    devices: self.devices(),
                    views: self.view_poses.len(),
                });
            }
        }
        Ok(())
    }

    /// Which entries of the parameter vector are refined.
    fn free_mask(&self, options: &RefineOptions) -> Vec<bool> {
        let mut free = Vec::new();
        for d in 0..self.devices() {
            free.extend([options.pinhole; 4]);
            let terms = options
                .device_distortion
                .as_ref()
                .and_then(|per| per.get(d))
                .unwrap_or(&options.distortion);
            free.extend(*terms);
        }
        let poses = self.device_poses.len().saturating_sub(1) + self.view_poses.len();
        free.extend(std::iter::repeat_n(true, poses * POSE_PARAMS));
        free
    }
}

/// Refines every parameter of `model` (subject to `options`) against `observations`.
pub fn refine(
    model: &RigModel,
    observations: &[Observation],
    options: &RefineOptions,
) -> Result<RigModel, BundleAdjustmentError> {
    model.check(observations)?;
    let free = model.free_mask(options);
    let residual_vector = |v: &DVector<f64>| -> Vec<f64> {
        let m = model.with_vector(v);
        m.residuals(observations)
            .into_iter()
            .flat_map(|r| match r {
                Some(r) => [r.x, r.y],
                None => [f64::NAN, f64::NAN],
            })
            .collect()
    };
    let outcome = minimise(residual_vector, model.to_vector(), &free, &options.lm)?;
    Ok(model.with_vector(&outcome.parameters))
}

/// Standard errors of each device's focal lengths `(fx, fy)`, pixels, for `model` fitted to
/// `observations` with `options` (see [`levenberg_marquardt::standard_errors`]; corners are taken
/// as no better than `sigma_floor_px`). A device whose focal lengths the views do not determine
/// at all (singular normal equations) gets infinite errors.
pub fn focal_standard_errors(
    model: &RigModel,
    observations: &[Observation],
    options: &RefineOptions,
    sigma_floor_px: f64,
) -> Vec<(f64, f64)> {
    let residual_vector = |v: &DVector<f64>| -> Vec<f64> {
        model
            .with_vector(v)
            .residuals(observations)
            .into_iter()
            .flat_map(|r| r.map_or([f64::NAN; 2], |r| [r.x, r.y]))
            .collect()
    };
    let errors = levenberg_marquardt::standard_errors(
        residual_vector,
        &model.to_vector(),
        &model.free_mask(options),
        sigma_floor_px,
    );
    (0..model.devices())
        .map(|d| {
            let error = |i: usize| {
                errors
                    .as_ref()
                    .and_then(|e| e[d * INTRINSIC_PARAMS + i])
                    .unwrap_or(f64::INFINITY)
            };
            (error(0), error(1))
        })
        .collect()
}

/// Root mean square of the residual lengths (OpenCV's reprojection RMS), `None` when empty.
pub fn rms(residuals: impl IntoIterator<Item = Vector2<f64>>) -> Option<f64> {
    let (sum, n) = residuals
        .into_iter()
        .fold((0.0, 0usize), |(s, n), r| (s + r.norm_squared(), n + 1));
    (n > 0).then(|| (sum / n as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn board_points() -> Vec<Vector3<f64>> {
        (0..63)
            .map(|i| Vector3::new((i % 9) as f64 * 30.0, (i / 9) as f64 * 30.0, 0.0))
            .collect()
    }

    #[test]
    fn joint_refinement_recovers_a_perturbed_two_device_rig() {
        let truth = RigModel {
            intrinsics: vec![
                Intrinsics {
                    fx: 1400.0,
                    fy: 1410.0,
                    cx: 630.0,
                    cy: 500.0,
                    distortion: [-0.12, 0.08, 0.001, -0.0005, 0.0],
                },
                Intrinsics {
                    fx: 1800.0,
                    fy: 1790.0,
                    cx: 512.0,
                    cy: 700.0,
                    distortion: [0.02, -0.03, 0.0, 0.0, 0.0],
                },
            ],
            device_poses: vec![
                Pose::identity(),
                Pose {
                    rotation: Vector3::new(0.05, -0.2, 0.01),
                    translation: Vector3::new(150.0, -20.0, 10.0),
                },
            ],
            view_poses: (0..5)
                .map(|j| Pose {
                    rotation: Vector3::new(
                        0.3 * (j as f64 - 2.0) * 0.5,
                        0.2 * ((j % 3) as f64 - 1.0),
                        0.05 * j as f64,
                    ),
                    translation: Vector3::new(-120.0, -90.0, 800.0 + 30.0 * j as f64),
                })
                .collect(),
        };
        let observations: Vec<Observation> = (0..5)
            .flat_map(|view| (0..2).map(move |device| (view, device)))
            .flat_map(|(view, device)| {
                let truth = &truth;
                board_points().into_iter().map(move |board| Observation {
                    device,
                    view,
                    board,
                    pixel: truth.project(device, view, &board).unwrap(),
                })
            })
            .collect();
        let mut start = truth.clone();
        start.intrinsics[0].fx *= 1.03;
        start.intrinsics[1].cy += 15.0;
        start.intrinsics[0].distortion = [0.0; 5];
        start.device_poses[1].translation.x += 8.0;
        start.view_poses[2].rotation.y += 0.02;
        let options = RefineOptions {
            distortion: [true, true, true, true, false],
            ..RefineOptions::default()
        };
        let fitted = refine(&start, &observations, &options).unwrap();
        let rms_px = rms(fitted.residuals(&observations).into_iter().flatten()).unwrap();
        assert!(rms_px < 1e-6, "rms {rms_px}");
        assert!((fitted.intrinsics[0].fx - 1400.0).abs() < 1e-4);
        assert!((fitted.intrinsics[1].cy - 700.0).abs() < 1e-4);
        assert!((fitted.device_poses[1].translation.x - 150.0).abs() < 1e-4);
        assert!(matches!(
            refine(
                &start,
                &[Observation {
                    device: 2,
                    ..observations[0]
                }],
                &options
            ),
            Err(BundleAdjustmentError::BadIndex { .. })
        ));
    }
}
