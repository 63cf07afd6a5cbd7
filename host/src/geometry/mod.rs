//! Geometry from structured light: Gray-code decoding (`gray_code`), loading of the code frames
//! from capture folders or OpenCV-ordered sequences (`code_frames`), and synthetic code frames with
//! a known mapping for tests and benchmarks (`synthetic`).

pub mod code_frames;
pub mod gray_code;
pub mod synthetic;
