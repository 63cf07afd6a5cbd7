//! Camera and projector calibration from chessboard poses (DESIGN sections 3 and 4, stage 2):
//! corner detection, Zhang's initialisation, projector corners by local homographies, bundle
//! adjustment, and OpenCV FileStorage import/export.

pub mod bundle_adjustment;
pub mod chessboard;
pub mod homography;
pub mod levenberg_marquardt;
pub mod local_homography;
pub mod opencv_storage;
pub mod pose_measurement;
pub mod procam;
pub mod zhang;
