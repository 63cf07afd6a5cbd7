//! Computer vision on booth captures: Gray-code decoding and triangulation (`geometry`), camera and
//! projector calibration from chessboard poses (`chessboard_calibration`), and photometry
//! (direct/global separation, photometric stereo, projector response).
//!
//! Depends on `mlsss-core` only.

pub mod chessboard_calibration;
pub mod geometry;
pub mod photometry;
pub mod symmetric_eigen3;
