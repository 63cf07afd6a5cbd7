//! MLSSS: measuring and rendering the multi-layered subsurface scattering of human skin from a
//! booth of four projectors and one camera. This crate is the application layer: the pipeline
//! stages, their evaluation, the demo and its report, and the `mlsss` command line.
//!
//! The layers below it, each a crate that may depend only on those listed before it:
//! `mlsss-core` (booth, calibration model, capture folders, image files), `mlsss-mc` (Monte Carlo
//! transport), `mlsss-rig` (controller and acquisition), `mlsss-vision` (decoding, calibration,
//! photometry), `mlsss-layer-model` (profiles, EM, relighting) and `mlsss-virtual-booth` (the
//! simulator). They are re-exported here so one dependency gives the whole library.

pub use mlsss_core::{atomic_file, booth, calibration, capture, imageio, resources, special};
pub use mlsss_layer_model as layer_model;
pub use mlsss_mc as mc;
pub use mlsss_rig as rig;
pub use mlsss_virtual_booth as virtual_booth;
pub use mlsss_vision::{chessboard_calibration, geometry, photometry};

pub mod demo;
pub mod evaluate;
pub mod pipeline;
pub mod pose_calibration;
pub mod quality_sweep;
pub mod report;
