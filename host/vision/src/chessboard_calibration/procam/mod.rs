//! Projector-camera calibration from chessboard poses: the camera by Zhang's method, each projector
//! as an inverse camera from its board corners found through Gray-code correspondences (Moreno &
//! Taubin 2012), then a joint bundle adjustment of camera, projectors, projector poses and board
//! poses. Bad input is reported, never silently used: a pose whose board was not found is skipped,
//! a pose whose corners do not fit the others is dropped, and every such decision is in the report.
//!
//! Conventions
//! - World frame = camera frame (camera R = I, t = 0), millimetres.
//! - Board points `(c * square, r * square, 0)` for corner column c and row r (row-major order, as
//!   [`super::chessboard`] returns them).
//! - RMS figures are OpenCV's: root mean square of the Euclidean reprojection error, in pixels of
//!   the device that measured the point.

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::Serialize;

use super::bundle_adjustment::{
    BundleAdjustmentError, Observation, Pose, RefineOptions, RigModel, focal_standard_errors,
    refine, rms,
};
use super::homography::{HomographyError, fit_homography};
use super::zhang::{ZhangError, intrinsics_from_homographies, pose_from_homography};
use mlsss_core::calibration::{
    Calibration, DeviceCalibration, Extrinsics, Intrinsics, ProjectorCalibration,
};
use mlsss_core::capture::folder::CaptureManifest;

/// Why a calibration could not be made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ProcamError {
    /// Too few poses survived for a device.
    #[error("{device}: only {usable} usable board poses, at least {needed} are needed ({detail})")]
    TooFewPoses {
        device: String,
        usable: usize,
        needed: usize,
        detail: String,
    },
    /// The closed-form initialisation failed.
    #[error("{device}: {source}")]
    Initialisation { device: String, source: ZhangError },
    /// The views leave the focal length undetermined (e.g. every board facing the same way).
    #[error(
        "{device}: the board poses determine the focal length only to +/-{relative_percent:.0} % \
         (fx {fx:.0} px): tilt the board by 10-30 degrees about both of its axes between poses \
         instead of only moving it"
    )]
    FocalUnobservable {
        device: String,
        fx: f64,
        relative_percent: f64,
    },
    /// The non-linear refinement failed.
    #[error("{device}: {source}")]
    Refinement {
        device: String,
        source: BundleAdjustmentError,
    },
}

/// The chessboard: inner corners and square size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardSpec {
    pub cols: usize,
    pub rows: usize,
    pub square_mm: f64,
}

impl BoardSpec {
    /// The board a simulated calibration capture shows, from its manifest's `source.board`
    /// (`inner_corners: [cols, rows]`, `square_mm`); `None` for a real capture, which does not
    /// record it.
    pub fn from_manifest(manifest: &CaptureManifest) -> Option<Self> {
        let board = &manifest.source["board"];
        let corners = board["inner_corners"].as_array()?;
        let count = |i: usize| corners.get(i)?.as_u64().map(|v| v as usize);
        Some(Self {
            cols: count(0)?,
            rows: count(1)?,
            square_mm: board["square_mm"].as_f64()?,
        })
    }

    /// Board points in row-major corner order.
    pub fn points(&self) -> Vec<Vector3<f64>> {
        (0..self.rows)
            .flat_map(|r| {
                (0..self.cols).map(move |c| {
                    Vector3::new(c as f64 * self.square_mm, r as f64 * self.square_mm, 0.0)
                })
            })
            .collect()
    }
}

/// What was measured in one pose.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseCorners {
    /// Name for reports (usually the capture folder).
    pub name: String,
    /// Camera pixel of every board corner (row-major), or why the board was not found.
    pub camera: Result<Vec<Vector2<f64>>, String>,
    /// Per projector: projector pixel of every board corner, `None` where it could not be
    /// measured (too few decoded pixels around it).
    pub projectors: Vec<Vec<Option<Vector2<f64>>>>,
}

/// Image size of a device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageSize {
    pub width: u32,
    pub height: u32,
}

/// Options of the calibration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProcamOptions {
    /// Distortion coefficients `[k1, k2, p1, p2, k3]` that may be estimated (others stay 0).
    pub distortion: [bool; 5],
    /// Choose, per device, the fewest of the allowed terms the corners support (see
    /// `select_distortion`) instead of estimating all of them.
    pub select_distortion: bool,
    /// A pose (or one projector's view of it) is dropped when its RMS exceeds both this many
    /// pixels and `outlier_factor` times the median of the poses.
    pub outlier_floor_px: f64,
    pub outlier_factor: f64,
    /// A projector view of a pose needs at least this fraction of the board's corners.
    pub min_projector_corner_fraction: f64,
}

impl Default for ProcamOptions {
    fn default() -> Self {
        Self {
            distortion: [true; 5],
            select_distortion: true,
            outlier_floor_px: 1.0,
            outlier_factor: 4.0,
            min_projector_corner_fraction: 0.5,
        }
    }
}

/// What happened to one pose.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PoseReport {
    pub name: String,
    /// Whether the camera corners of this pose are in the final calibration.
    pub used: bool,
    /// Why the pose was skipped or dropped.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Camera RMS of this pose in the final joint model.
    pub camera_rms_px: Option<f64>,
    /// Per projector: RMS of this pose in the final model (`None` when not used).
    pub projector_rms_px: Vec<Option<f64>>,
    /// Per projector: corners measured / used.
    pub projector_corners: Vec<usize>,
    /// Per projector: why this projector's view of the pose was not used.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub projector_reasons: Vec<String>,
}

/// RMS of the separate per-device fits, before the joint refinement (comparable to OpenCV's
/// `calibrateCamera` for each device).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SeparateFits {
    pub camera_rms_px: f64,
    pub projector_rms_px: Vec<f64>,
}

/// The result: the calibration and its diagnostics.
#[derive(Debug, Clone, PartialEq)]
pub struct ProcamResult {
    pub calibration: Calibration,
    /// Camera RMS in the final joint model.
    pub camera_rms_px: f64,
    /// Per projector RMS in the final joint model.
    pub projector_rms_px: Vec<f64>,
    /// RMS over every camera and projector observation of the joint model.
    pub stereo_rms_px: f64,
    pub separate: SeparateFits,
    pub poses: Vec<PoseReport>,
    /// Per device (camera, then projectors): which of `[k1, k2, p1, p2, k3]` were estimated.
    pub distortion_terms: Vec<[bool; 5]>,
}

/// A fit of one device alone (Zhang + refinement) on a set of views.
#[derive(Debug, Clone)]
struct DeviceFit {
    intrinsics: Intrinsics,
    /// Board -> device pose per view (aligned with the `views` given).
    poses: Vec<Pose>,
    /// RMS per view.
    view_rms: Vec<f64>,
    rms: f64,
    /// The distortion terms estimated.
    distortion: [bool; 5],
}

/// One device's measurements in one view: (board point, pixel) pairs.
type ViewPoints = Vec<(Vector3<f64>, Vector2<f64>)>;

/// Fits one device alone: homographies, Zhang, pose per view, then Levenberg-Marquardt.
fn fit_device(
    device: &str,
    views: &[ViewPoints],
    size: ImageSize,
    distortion: [bool; 5],
    select: bool,
) -> Result<DeviceFit, ProcamError> {
    let model = closed_form_model(device, views, size)?;
    let observations: Vec<Observation> = views
        .iter()
        .enumerate()
        .flat_map(|(view, points)| {
            points.iter().map(move |&(board, pixel)| Observation {
                device: 0,
                view,
                board,
                pixel,
            })
        })
        .collect();
    let (model, distortion) = refine_device(device, &model, &observations, distortion, select)?;
    refuse_unobservable_focal(device, &model, &observations, distortion)?;
    let residuals = model.residuals(&observations);
    let view_rms = (0..views.len())
        .map(|v| {
            rms(observations
                .iter()
                .zip(&residuals)
                .filter(|(o, _)| o.view == v)
                .map(|(_, r)| r.unwrap_or(Vector2::repeat(1e6))))
            .unwrap_or(0.0)
        })
        .collect();
    Ok(DeviceFit {
        intrinsics: model.intrinsics[0],
        poses: model.view_poses,
        view_rms,
        rms: rms(residuals
            .into_iter()
            .map(|r| r.unwrap_or(Vector2::repeat(1e6))))
        .unwrap_or(0.0),
        distortion,
    })
}

/// Corner positions are taken as no better than this, pixels, when judging how well the views
/// determine the focal length: exact (synthetic) corners must not hide a degenerate pose set.
const CORNER_SIGMA_FLOOR_PX: f64 = 0.05;

/// A focal length known to worse than this relative standard error is refused. Well-spread poses
/// give about 0.1-0.5 %; boards that all face one way give tens of percent or infinity.
const MAX_FOCAL_RELATIVE_ERROR: f64 = 0.05;

/// Refuses a fit whose focal length the views do not determine: translating a board without
/// tilting it leaves the focal length unobservable (Zhang 2000, section 3.3), and the fit then
/// reports any focal length with a small RMS (fx 63 px for a true 1 500 on five parallel boards).
fn refuse_unobservable_focal(
    device: &str,
    model: &RigModel,
    observations: &[Observation],
    distortion: [bool; 5],
) -> Result<(), ProcamError> {
    let options = RefineOptions {
        distortion,
        ..RefineOptions::default()
    };
    let errors = focal_standard_errors(model, observations, &options, CORNER_SIGMA_FLOOR_PX);
    let k = &model.intrinsics[0];
    let (fx_error, fy_error) = errors
        .first()
        .copied()
        .unwrap_or((f64::INFINITY, f64::INFINITY));
    let relative = (fx_error / k.fx.abs()).max(fy_error / k.fy.abs());
    if relative <= MAX_FOCAL_RELATIVE_ERROR {
        return Ok(());
    }
    Err(ProcamError::FocalUnobservable {
        device: device.into(),
        fx: k.fx,
        relative_percent: if relative.is_finite() {
            100.0 * relative
        } else {
            f64::INFINITY
        },
    })
}

/// Two views whose shared corners are on average closer than this, pixels, show the board in
/// the same place: noise alone separates them (a board held still, or one pose copied).
const SAME_VIEW_PX: f64 = 0.5;

/// Refuses a set of views that shows the board in fewer than two distinct places: the same view
/// again adds no constraint, and a closed form on one view fits any focal length with a tiny RMS
/// (three copies of one pose gave fx 210 795 for a true 2 000).
fn refuse_repeated_views(device: &str, views: &[ViewPoints]) -> Result<(), ProcamError> {
    let mut distinct: Vec<usize> = Vec::new();
    let mut repeated: Vec<(usize, usize)> = Vec::new();
    for (i, view) in views.iter().enumerate() {
        match distinct
            .iter()
            .find(|&&j| mean_shared_corner_distance(view, &views[j]) < SAME_VIEW_PX)
        {
            Some(&j) => repeated.push((j, i)),
            None => distinct.push(i),
        }
    }
    if distinct.len() >= 2 || views.len() < 2 {
        return Ok(());
    }
    let pairs: Vec<String> = repeated
        .iter()
        .map(|(a, b)| format!("views {a} and {b}"))
        .collect();
    Err(ProcamError::TooFewPoses {
        device: device.into(),
        usable: distinct.len(),
        needed: 2,
        detail: format!(
            "{} show the board in the same place (shared corners within {SAME_VIEW_PX} px): \
             move and tilt the board between poses",
            pairs.join(", ")
        ),
    })
}

/// Mean pixel distance between the corners two views share (infinite when they share none).
fn mean_shared_corner_distance(a: &ViewPoints, b: &ViewPoints) -> f64 {
    let (sum, count) = a
        .iter()
        .filter_map(|(board, pixel)| {
            b.iter()
                .find(|(other, _)| other == board)
                .map(|(_, other_pixel)| (pixel - other_pixel).norm())
        })
        .fold((0.0, 0usize), |(s, n), d| (s + d, n + 1));
    if count == 0 {
        f64::INFINITY
    } else {
        sum / count as f64
    }
}

/// The closed-form start of a one-device fit: a homography per view, Zhang's pinhole (no
/// distortion) and the board pose of every view.
fn closed_form_model(
    device: &str,
    views: &[ViewPoints],
    size: ImageSize,
) -> Result<RigModel, ProcamError> {
    refuse_repeated_views(device, views)?;
    let homographies: Vec<Matrix3<f64>> = views
        .iter()
        .map(|v| {
            let src: Vec<Vector2<f64>> = v.iter().map(|(b, _)| b.xy()).collect();
            let dst: Vec<Vector2<f64>> = v.iter().map(|(_, p)| *p).collect();
            fit_homography(&src, &dst)
        })
        .collect::<Result<_, HomographyError>>()
        .map_err(|e| ProcamError::TooFewPoses {
            device: device.into(),
            usable: 0,
            needed: 3,
            detail: e.to_string(),
        })?;
    let pinhole =
        intrinsics_from_homographies(&homographies, size.width, size.height).map_err(|source| {
            ProcamError::Initialisation {
                device: device.into(),
                source,
            }
        })?;
    let k = pinhole.k_matrix();
    let poses = homographies
        .iter()
        .map(|h| {
            pose_from_homography(&k, h)
                .map(|(r, t)| Pose::from_rotation(&r, t))
                .ok_or(ProcamError::Initialisation {
                    device: device.into(),
                    source: ZhangError::Degenerate,
                })
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(RigModel {
        intrinsics: vec![Intrinsics {
            fx: pinhole.fx,
            fy: pinhole.fy,
            cx: pinhole.cx,
            cy: pinhole.cy,
            distortion: [0.0; 5],
        }],
        device_poses: vec![Pose::identity()],
        view_poses: poses,
    })
}

/// A one-device model refined from its closed form: pinhole and poses first, then with the
/// `distortion` terms (or, with `select`, the fewest nested sets of them the corners support).
/// Returns the model and the terms it estimated.
fn refine_device(
    device: &str,
    model: &RigModel,
    observations: &[Observation],
    distortion: [bool; 5],
    select: bool,
) -> Result<(RigModel, [bool; 5]), ProcamError> {
    let refine_err = |source| ProcamError::Refinement {
        device: device.into(),
        source,
    };
    // Pinhole and poses first, then with distortion: a safer path from the closed form.
    let pinhole_only = RefineOptions {
        distortion: [false; 5],
        ..RefineOptions::default()
    };
    let pinhole_model = refine(model, observations, &pinhole_only).map_err(refine_err)?;
    let candidates = if select {
        nested_distortion_sets(distortion)
    } else {
        vec![distortion]
    };
    let fits = candidates
        .iter()
        .map(|&terms| {
            let options = RefineOptions {
                distortion: terms,
                ..RefineOptions::default()
            };
            refine(&pinhole_model, observations, &options).map_err(refine_err)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let squared_sums: Vec<f64> = fits
        .iter()
        .map(|m| {
            m.residuals(observations)
                .into_iter()
                .map(|r| r.map_or(1e12, |r| r.norm_squared()))
                .sum()
        })
        .collect();
    let chosen = select_distortion(&candidates, &squared_sums, observations.len());
    Ok((fits[chosen].clone(), candidates[chosen]))
}

/// Names of the distortion terms set in `terms` (`[k1, k2, p1, p2, k3]` order), for reports.
pub fn distortion_term_names(terms: &[bool; 5]) -> Vec<&'static str> {
    ["k1", "k2", "p1", "p2", "k3"]
        .into_iter()
        .zip(terms)
        .filter_map(|(name, &on)| on.then_some(name))
        .collect()
}

/// Corner precision below which a better fit is not evidence of a real term: residuals are
/// counted as at least this large (exact synthetic corners would otherwise reward fitting the
/// optimiser's round-off).
const CORNER_NOISE_FLOOR_PX: f64 = 1e-3;

/// The nested distortion models tried, simplest first, restricted to the `allowed` terms:
/// none, k1, k1 k2, k1 k2 p1 p2, k1 k2 p1 p2 k3 (the order in which real lenses need them).
fn nested_distortion_sets(allowed: [bool; 5]) -> Vec<[bool; 5]> {
    let levels = [
        [false; 5],
        [true, false, false, false, false],
        [true, true, false, false, false],
        [true, true, true, true, false],
        [true; 5],
    ];
    let mut sets: Vec<[bool; 5]> = Vec::new();
    for level in levels {
        let terms: [bool; 5] = std::array::from_fn(|i| level[i] && allowed[i]);
        if !sets.contains(&terms) {
            sets.push(terms);
        }
    }
    sets
}

/// Index of the distortion model with the lowest Bayesian information criterion
/// `n ln(RSS / n) + p ln n` over `n` residual coordinates (two per observation), `p` being the
/// number of distortion terms. A term is kept only when it explains the corners markedly better:
/// with a narrow field of view the high-order radial terms and the tangential ones barely move
/// any corner, and estimating them anyway trades them against the focal length and principal
/// point (a 5-pose fit then put k3 at -1700 and biased depth by 0.1 %).
fn select_distortion(candidates: &[[bool; 5]], squared_sums: &[f64], observations: usize) -> usize {
    let n = (2 * observations).max(1) as f64;
    let floor = n * CORNER_NOISE_FLOOR_PX * CORNER_NOISE_FLOOR_PX;
    let bic = |terms: &[bool; 5], rss: f64| {
        let p = terms.iter().filter(|&&t| t).count() as f64;
        n * (rss.max(floor) / n).ln() + p * n.ln()
    };
    candidates
        .iter()
        .zip(squared_sums)
        .enumerate()
        .min_by(|(_, (a, ra)), (_, (b, rb))| bic(a, **ra).total_cmp(&bic(b, **rb)))
        .map_or(0, |(i, _)| i)
}

/// The view to drop as an outlier, if any: the worst one, when it is far above the median.
fn outlier_view(view_rms: &[f64], options: &ProcamOptions) -> Option<usize> {
    let mut sorted = view_rms.to_vec();
    sorted.sort_by(f64::total_cmp);
    let median = *sorted.get(sorted.len() / 2)?;
    let (worst, &worst_rms) = view_rms
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))?;
    (worst_rms > options.outlier_floor_px && worst_rms > options.outlier_factor * median)
        .then_some(worst)
}

/// Minimum number of views for a device fit.
const MIN_VIEWS: usize = 3;

/// A device fit with the views it kept and those it dropped (index, RMS).
struct RobustFit {
    fit: DeviceFit,
    kept: Vec<usize>,
    dropped: Vec<(usize, f64)>,
}

/// Fits a device on the views in `candidates` (indices into `views`), dropping outlier views one
/// at a time. Returns the fit, the indices kept, and the dropped ones with their RMS.
fn fit_device_robust(
    device: &str,
    views: &[ViewPoints],
    candidates: Vec<usize>,
    size: ImageSize,
    options: &ProcamOptions,
) -> Result<RobustFit, ProcamError> {
    let mut kept = candidates;
    let mut dropped = Vec::new();
    loop {
        if kept.len() < MIN_VIEWS {
            return Err(ProcamError::TooFewPoses {
                device: device.into(),
                usable: kept.len(),
                needed: MIN_VIEWS,
                detail: format!("{} dropped as outliers", dropped.len()),
            });
        }
        let subset: Vec<ViewPoints> = kept.iter().map(|&i| views[i].clone()).collect();
        let fit = fit_device(
            device,
            &subset,
            size,
            options.distortion,
            options.select_distortion,
        )?;
        match outlier_view(&fit.view_rms, options) {
            Some(worst) if kept.len() > MIN_VIEWS => {
                dropped.push((kept[worst], fit.view_rms[worst]));
                kept.remove(worst);
            }
            _ => {
                return Ok(RobustFit { fit, kept, dropped });
            }
        }
    }
}

/// Calibrates a camera and its projectors from chessboard poses.
pub fn calibrate_procam(
    poses: &[PoseCorners],
    board: &BoardSpec,
    camera_size: ImageSize,
    projector_sizes: &[ImageSize],
    options: &ProcamOptions,
) -> Result<ProcamResult, ProcamError> {
    let points = board.points();
    let mut reports = initial_reports(poses, projector_sizes.len());
    let camera_views = camera_views(poses, &points, &mut reports);
    let camera = fit_camera(&camera_views, camera_size, options, &mut reports)?;
    let mut projectors = Vec::new();
    for (k, size) in projector_sizes.iter().enumerate() {
        let views = projector_views(poses, &points, k);
        projectors.push(fit_projector(
            k,
            views,
            &camera.kept,
            *size,
            points.len(),
            options,
            &mut reports,
        )?);
    }
    let (model, distortion_terms) = initial_joint_model(&camera, &projectors);
    let observations = joint_observations(&camera_views, &camera.kept, &projectors);
    let joint = refine(
        &model,
        &observations,
        &RefineOptions {
            distortion: options.distortion,
            device_distortion: Some(distortion_terms.clone()),
            ..RefineOptions::default()
        },
    )
    .map_err(|source| ProcamError::Refinement {
        device: "joint refinement".into(),
        source,
    })?;
    let residuals = JointResiduals::new(&joint, observations);
    residuals.report_poses(&camera.kept, projector_sizes.len(), &mut reports);
    let camera_rms_px = residuals.rms_where(&|o| o.device == 0).unwrap_or(0.0);
    let projector_rms_px: Vec<f64> = (0..projector_sizes.len())
        .map(|k| residuals.rms_where(&|o| o.device == k + 1).unwrap_or(0.0))
        .collect();
    let stereo_rms_px = rms(residuals.residuals.iter().copied()).unwrap_or(0.0);
    let calibration = joint_calibration(
        &joint,
        camera_size,
        projector_sizes,
        camera_rms_px,
        &projector_rms_px,
    );
    Ok(ProcamResult {
        calibration,
        camera_rms_px,
        projector_rms_px,
        stereo_rms_px,
        separate: SeparateFits {
            camera_rms_px: camera.fit.rms,
            projector_rms_px: projectors.iter().map(|p| p.fit.rms).collect(),
        },
        poses: reports,
        distortion_terms,
    })
}

/// One report per pose, nothing used yet; poses whose board was not found say so.
fn initial_reports(poses: &[PoseCorners], projectors: usize) -> Vec<PoseReport> {
    poses
        .iter()
        .map(|p| PoseReport {
            name: p.name.clone(),
            used: false,
            reason: p
                .camera
                .as_ref()
                .err()
                .map(|e| format!("chessboard not found: {e}")),
            camera_rms_px: None,
            projector_rms_px: vec![None; projectors],
            projector_corners: vec![0; projectors],
            projector_reasons: Vec::new(),
        })
        .collect()
}

/// Camera views: every pose whose board was found with the full corner count (empty for the
/// others, whose reports say why).
fn camera_views(
    poses: &[PoseCorners],
    points: &[Vector3<f64>],
    reports: &mut [PoseReport],
) -> Vec<ViewPoints> {
    let camera_views: Vec<ViewPoints> = poses
        .iter()
        .map(|p| match &p.camera {
            Ok(c) if c.len() == points.len() => {
                points.iter().copied().zip(c.iter().copied()).collect()
            }
            _ => Vec::new(),
        })
        .collect();
    for (report, view) in reports.iter_mut().zip(&camera_views) {
        if view.is_empty() && report.reason.is_none() {
            report.reason = Some(format!("expected {} camera corners", points.len()));
        }
    }
    camera_views
}

/// The camera alone on every pose with a view, outlier poses dropped (and reported).
fn fit_camera(
    camera_views: &[ViewPoints],
    camera_size: ImageSize,
    options: &ProcamOptions,
    reports: &mut [PoseReport],
) -> Result<RobustFit, ProcamError> {
    let candidates: Vec<usize> = (0..camera_views.len())
        .filter(|&i| !camera_views[i].is_empty())
        .collect();
    let RobustFit { fit, kept, dropped } =
        fit_device_robust("camera", camera_views, candidates, camera_size, options)?;
    for &(i, view_rms) in &dropped {
        reports[i].reason = Some(format!(
            "bad pose: camera reprojection RMS {view_rms:.2} px is far above the other poses'"
        ));
    }
    Ok(RobustFit { fit, kept, dropped })
}

/// Projector `k`'s views: per pose, the board corners it measured.
fn projector_views(poses: &[PoseCorners], points: &[Vector3<f64>], k: usize) -> Vec<ViewPoints> {
    poses
        .iter()
        .map(|p| {
            p.projectors
                .get(k)
                .map(|corners| {
                    points
                        .iter()
                        .zip(corners)
                        .filter_map(|(b, c)| c.map(|c| (*b, c)))
                        .collect()
                })
                .unwrap_or_default()
        })
        .collect()
}

/// A projector's separate fit, with its views (one per pose) and the poses it kept.
struct ProjectorFit {
    fit: DeviceFit,
    views: Vec<ViewPoints>,
    kept: Vec<usize>,
}

/// Projector `k` alone on the poses the camera kept where it measured enough of the board's
/// `corners`, outlier views dropped; every pose left out is reported.
fn fit_projector(
    k: usize,
    views: Vec<ViewPoints>,
    camera_kept: &[usize],
    size: ImageSize,
    corners: usize,
    options: &ProcamOptions,
    reports: &mut [PoseReport],
) -> Result<ProjectorFit, ProcamError> {
    let name = format!("projector {k}");
    let min_corners =
        ((corners as f64 * options.min_projector_corner_fraction).ceil() as usize).max(6);
    let mut candidates = Vec::new();
    for &i in camera_kept {
        reports[i].projector_corners[k] = views[i].len();
        if views[i].len() >= min_corners {
            candidates.push(i);
        } else {
            reports[i].projector_reasons.push(format!(
                "{name}: only {} of {} corners measured",
                views[i].len(),
                corners
            ));
        }
    }
    let RobustFit { fit, kept, dropped } =
        fit_device_robust(&name, &views, candidates, size, options)?;
    for (i, view_rms) in dropped {
        reports[i].projector_reasons.push(format!(
            "{name}: bad view, reprojection RMS {view_rms:.2} px is far above the other poses'"
        ));
    }
    Ok(ProjectorFit { fit, views, kept })
}

/// The joint model's start from the separate fits: camera = device 0, projector k = device
/// k + 1; views = the camera-kept poses. Also the distortion terms of every device.
fn initial_joint_model(
    camera: &RobustFit,
    projectors: &[ProjectorFit],
) -> (RigModel, Vec<[bool; 5]>) {
    let mut device_poses = vec![Pose::identity()];
    for p in projectors {
        device_poses.push(initial_device_pose(
            &camera.fit,
            &camera.kept,
            &p.fit,
            &p.kept,
        ));
    }
    let distortion_terms: Vec<[bool; 5]> = std::iter::once(camera.fit.distortion)
        .chain(projectors.iter().map(|p| p.fit.distortion))
        .collect();
    let model = RigModel {
        intrinsics: std::iter::once(camera.fit.intrinsics)
            .chain(projectors.iter().map(|p| p.fit.intrinsics))
            .collect(),
        device_poses,
        view_poses: camera.fit.poses.clone(),
    };
    (model, distortion_terms)
}

/// Every observation of the joint model: the camera's in its kept poses, then each projector's
/// in its kept poses that the camera kept too.
fn joint_observations(
    camera_views: &[ViewPoints],
    camera_kept: &[usize],
    projectors: &[ProjectorFit],
) -> Vec<Observation> {
    let view_of_pose = |pose: usize| camera_kept.iter().position(|&i| i == pose);
    let mut observations = Vec::new();
    for (view, &pose) in camera_kept.iter().enumerate() {
        observations.extend(
            camera_views[pose]
                .iter()
                .map(|&(board, pixel)| Observation {
                    device: 0,
                    view,
                    board,
                    pixel,
                }),
        );
    }
    for (k, p) in projectors.iter().enumerate() {
        for &pose in &p.kept {
            let Some(view) = view_of_pose(pose) else {
                continue;
            };
            observations.extend(p.views[pose].iter().map(|&(board, pixel)| Observation {
                device: k + 1,
                view,
                board,
                pixel,
            }));
        }
    }
    observations
}

/// The joint model's reprojection residual of every observation (1e6 px where it does not
/// project).
struct JointResiduals {
    observations: Vec<Observation>,
    residuals: Vec<Vector2<f64>>,
}

impl JointResiduals {
    fn new(joint: &RigModel, observations: Vec<Observation>) -> Self {
        let residuals: Vec<Vector2<f64>> = joint
            .residuals(&observations)
            .into_iter()
            .map(|r| r.unwrap_or(Vector2::repeat(1e6)))
            .collect();
        Self {
            observations,
            residuals,
        }
    }

    /// RMS of the observations `pred` selects; `None` without any.
    fn rms_where(&self, pred: &dyn Fn(&Observation) -> bool) -> Option<f64> {
        rms(self
            .observations
            .iter()
            .zip(&self.residuals)
            .filter(|(o, _)| pred(o))
            .map(|(_, r)| *r))
    }

    /// Marks the camera-kept poses used, with their RMS per device.
    fn report_poses(&self, camera_kept: &[usize], projectors: usize, reports: &mut [PoseReport]) {
        for (view, &pose) in camera_kept.iter().enumerate() {
            let r = &mut reports[pose];
            r.used = true;
            r.camera_rms_px = self.rms_where(&|o| o.device == 0 && o.view == view);
            for k in 0..projectors {
                r.projector_rms_px[k] = self.rms_where(&|o| o.device == k + 1 && o.view == view);
            }
        }
    }
}

/// The refined joint model as a calibration with its RMS figures.
fn joint_calibration(
    joint: &RigModel,
    camera_size: ImageSize,
    projector_sizes: &[ImageSize],
    camera_rms_px: f64,
    projector_rms_px: &[f64],
) -> Calibration {
    let device = |d: usize, size: ImageSize| DeviceCalibration {
        width: size.width,
        height: size.height,
        intrinsics: joint.intrinsics[d],
        extrinsics: Extrinsics::from_rt(
            joint.device_poses[d].rotation_matrix().matrix(),
            &joint.device_poses[d].translation,
        ),
    };
    Calibration {
        camera: device(0, camera_size),
        camera_rms_px: Some(camera_rms_px),
        projectors: projector_sizes
            .iter()
            .enumerate()
            .map(|(k, &size)| ProjectorCalibration {
                device: device(k + 1, size),
                response: None,
                rms_px: Some(projector_rms_px[k]),
            })
            .collect(),
    }
}

/// Camera -> projector pose from the views both fits share: `T_pc = T_pb T_cb^-1` per view, then
/// the rotation vectors and translations are averaged (they agree closely for a good fit).
fn initial_device_pose(
    camera: &DeviceFit,
    camera_views: &[usize],
    projector: &DeviceFit,
    projector_views: &[usize],
) -> Pose {
    let estimates: Vec<Pose> = projector_views
        .iter()
        .enumerate()
        .filter_map(|(pi, pose)| {
            let ci = camera_views.iter().position(|c| c == pose)?;
            Some(projector.poses[pi].compose(&camera.poses[ci].inverse()))
        })
        .collect();
    let n = estimates.len().max(1) as f64;
    Pose {
        rotation: estimates
            .iter()
            .fold(Vector3::zeros(), |a, p| a + p.rotation)
            / n,
        translation: estimates
            .iter()
            .fold(Vector3::zeros(), |a, p| a + p.translation)
            / n,
    }
}

#[cfg(test)]
mod tests;
