//! Booth calibration from chessboard pose folders, the sequence `mlsss calibrate` and the demo
//! share: measure every pose (in parallel), check that the poses agree on the devices' sizes,
//! then calibrate camera and projectors together (`chessboard_calibration::procam`).

use std::path::PathBuf;

use rayon::prelude::*;

use mlsss_vision::chessboard_calibration::local_homography::LocalHomographyOptions;
use mlsss_vision::chessboard_calibration::pose_measurement::{
    BoardCorners, MeasuredPose, PoseLayout, PoseMeasurementError, measure_pose,
};
use mlsss_vision::chessboard_calibration::procam::{
    BoardSpec, ProcamError, ProcamOptions, ProcamResult, calibrate_procam,
};

/// Errors of [`calibrate_poses`].
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PoseCalibrationError {
    /// No pose folder was given.
    #[error("no calibration pose given")]
    NoPoses,
    /// A pose could not be measured.
    #[error(transparent)]
    Measurement(#[from] PoseMeasurementError),
    /// Two poses disagree on the camera or projector sizes.
    #[error("pose {pose} has a different camera or projector size than {first}")]
    SizeMismatch { pose: String, first: String },
    /// The calibration failed.
    #[error(transparent)]
    Procam(#[from] ProcamError),
}

/// The calibration of the poses and the poses whose chessboard the camera did not find (name,
/// reason): they are left out of the calibration.
#[derive(Debug, Clone)]
pub struct PoseCalibration {
    pub result: ProcamResult,
    pub board_not_found: Vec<(String, String)>,
}

/// Calibrates the booth from the pose folders `poses` (layout `layout`) of the chessboard
/// `board`. `on_measured` is called after each pose is measured (from worker threads).
pub fn calibrate_poses(
    poses: &[PathBuf],
    layout: PoseLayout,
    board: &BoardSpec,
    options: &ProcamOptions,
    on_measured: &(dyn Fn() + Sync),
) -> Result<PoseCalibration, PoseCalibrationError> {
    let corners = BoardCorners {
        cols: board.cols,
        rows: board.rows,
    };
    let measured = poses
        .par_iter()
        .map(|dir| {
            let pose = measure_pose(dir, layout, corners, &LocalHomographyOptions::default());
            on_measured();
            pose
        })
        .collect::<Result<Vec<MeasuredPose>, _>>()?;
    let first = measured.first().ok_or(PoseCalibrationError::NoPoses)?;
    if let Some(pose) = measured.iter().find(|pose| {
        pose.camera_size != first.camera_size || pose.projector_sizes != first.projector_sizes
    }) {
        return Err(PoseCalibrationError::SizeMismatch {
            pose: pose.corners.name.clone(),
            first: first.corners.name.clone(),
        });
    }
    let board_not_found = measured
        .iter()
        .filter_map(|m| {
            let reason = m.corners.camera.as_ref().err()?;
            Some((m.corners.name.clone(), reason.clone()))
        })
        .collect();
    let corner_sets: Vec<_> = measured.iter().map(|m| m.corners.clone()).collect();
    let result = calibrate_procam(
        &corner_sets,
        board,
        first.camera_size,
        &first.projector_sizes,
        options,
    )?;
    Ok(PoseCalibration {
        result,
        board_not_found,
    })
}
