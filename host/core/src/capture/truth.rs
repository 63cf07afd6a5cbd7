//! File names of the ground truth the virtual booth writes under `CAPTURE/truth/` (DESIGN
//! section 6). Readers (evaluation in every stage) and the writer (the simulator) use these helpers
//! so the names cannot drift apart.
//!
//! Conventions
//! - Images are camera-sized, pixel (x, y) = camera pixel, linear float EXR unless stated.
//! - Radiometric images use the frames' scale (linear camera value in [0, 1] before noise and
//!   quantisation), so they compare directly with decoded frames.
//! - Lengths in millimetres, world frame of `hardware/booth.toml`.
//! - Pixels not on the subject: depth 0, points and normals 0, mask 0.

use std::path::{Path, PathBuf};

use crate::capture::Pattern;

/// The true calibration (`calib::Calibration` JSON, with projector responses).
pub fn calibration(truth: &Path) -> PathBuf {
    truth.join("calibration.json")
}

/// 8-bit PNG: 255 where the camera sees the subject surface, 0 elsewhere.
pub fn mask(truth: &Path) -> PathBuf {
    truth.join("mask.png")
}

/// Single channel: camera-frame depth z (mm) of the surface seen by each pixel.
pub fn depth(truth: &Path) -> PathBuf {
    truth.join("depth.exr")
}

/// RGB = world-frame X, Y, Z (mm) of the surface point seen by each pixel.
pub fn points(truth: &Path) -> PathBuf {
    truth.join("points.exr")
}

/// RGB = world-frame unit surface normal (pointing out of the skin, towards the camera side).
pub fn normals(truth: &Path) -> PathBuf {
    truth.join("normals.exr")
}

/// RGB = (u, v, lit) for projector `k`: sub-pixel projector column and row of the surface point,
/// and 1 where that projector lights the point (not shadowed, inside its image), else 0.
pub fn projector_coords(truth: &Path, k: usize) -> PathBuf {
    truth.join(format!("proj{k}_coords.exr"))
}

/// Direct (single-bounce surface + specular) radiance under projector `k` showing `pattern`.
pub fn direct(truth: &Path, k: usize, pattern: &Pattern) -> PathBuf {
    truth.join(format!("proj{k}_direct_{}.exr", pattern.label()))
}

/// Global (subsurface) radiance under projector `k` showing `pattern`.
pub fn global(truth: &Path, k: usize, pattern: &Pattern) -> PathBuf {
    truth.join(format!("proj{k}_global_{}.exr", pattern.label()))
}

/// Material maps: RGB = (melanin, blood, stubble) fractions in [0, 1] relative to the preset.
pub fn material_maps(truth: &Path) -> PathBuf {
    truth.join("materials.exr")
}

/// Per-material, per-channel optical parameters (JSON).
pub fn optics(truth: &Path) -> PathBuf {
    truth.join("optics.json")
}

/// Light the other projectors' black level adds to every frame lit by projector `k` (camera
/// values, RGB): they show black, which still emits `black_level` of their white.
pub fn stray_light(truth: &Path, k: usize) -> PathBuf {
    truth.join(format!("proj{k}_stray.exr"))
}

/// Calibration target of a calibration capture (JSON): board geometry, pose, the inner corners
/// in world coordinates and their true camera pixels (distortion included).
pub fn target(truth: &Path) -> PathBuf {
    truth.join("target.json")
}
