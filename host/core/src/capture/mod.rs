//! Captures: the frame plan, the projected patterns, and the capture folder on disk (DESIGN
//! sections 3 and 8). Every producer (rig, virtual booth) and every reader (decode, separation,
//! profiles) goes through this module so they agree on frame order and pixel encoding.

pub mod exposure;
pub mod folder;
pub mod frame_plan;
pub mod patterns;
mod stored_png;
pub mod truth;

pub use exposure::{FrameNoise, ProjectorExposure};
pub use folder::{
    Capture, CaptureError, CaptureManifest, CaptureWriter, FrameSamples, TriggerRecord,
};
pub use frame_plan::{FramePlan, FrameSpec};
pub use patterns::{Axis, Pattern};
