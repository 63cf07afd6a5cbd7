//! MLSSS: measuring and rendering the multi-layered subsurface scattering of human skin from a
//! booth of four projectors and one camera.
//!
//! Modules mirror the architecture of `DESIGN.md`: the booth description and calibration model are
//! shared by everything; `capture` is the contract between producers (rig, virtual booth) and the
//! processing stages.

pub mod booth;
pub mod calib;
pub mod calibrate;
pub mod capture;
pub mod demo;
pub mod evaluate;
pub mod geometry;
pub mod imageio;
pub mod mc;
pub mod photometry;
pub mod pipeline;
pub mod report;
pub mod rig;
pub mod special;
pub mod subsurface;
pub mod virtual_booth;
