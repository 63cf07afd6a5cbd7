//! The base layer of MLSSS, shared by every other crate: the booth description, the calibration
//! model, the capture folder (the contract between the producers of frames, rig and virtual booth,
//! and the processing stages), image files, special functions, the one Gaussian blur and the
//! process's resource use.
//!
//! Nothing here knows about an algorithm; everything above may depend on it.

pub mod atomic_file;
pub mod booth;
pub mod calibration;
pub mod capture;
pub mod gaussian_blur;
pub mod imageio;
pub mod resources;
pub mod special;

#[cfg(test)]
mod reader_proptests;
