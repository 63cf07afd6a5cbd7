//! Geometry from structured light: Gray-code decoding (`gray_code`), loading of the code frames
//! from capture folders or OpenCV-ordered sequences (`code_frames`), and synthetic code frames with
//! a known mapping for tests and benchmarks (`synthetic`), triangulation and fusion across
//! projectors (`triangulation`), the pixel-grid mesh with its PLY and shaded preview (`grid_mesh`), and
//! the surface normals of a point map by local plane fits (`point_normals`).

pub mod code_frames;
pub mod gray_code;
pub mod grid_mesh;
pub mod point_normals;
pub mod synthetic;
pub mod triangulation;
