//! The virtual booth: renders captures of a described booth and subject, with noise, and writes
//! the ground truth beside them (DESIGN section 6). It is the reference every accuracy figure is
//! measured against, so it is built from physics that knows nothing of the MLSSS model:
//!
//! - geometry by ray casting (`subjects`, `head`, `scene`), shadows by rays to the projectors;
//! - projectors as pinholes with response curve, black level and defocus (`projector`);
//! - surface reflection as a rough dielectric specular lobe with Fresnel (`surface_reflection`);
//! - light below the surface from Monte Carlo exit responses of layered skin (`skin_optics`,
//!   `material_maps`, `subsurface`), blended by the material maps and interpolated over the angle
//!   of incidence;
//! - a camera with distortion, shot and read noise (normal deviates of `mlsss_mc::NormalStream`),
//!   saturation and 12-bit codes (`camera`).

pub mod camera;
pub mod complement_frames;
pub mod frame_render;
pub mod head;
pub mod material_maps;
pub mod metering;
pub mod projector;
pub mod response_cache;
pub mod scene;
pub mod simulation;
pub mod skin_optics;
pub mod subjects;
pub mod subsurface_transport;
pub mod surface_reflection;
pub mod truth_writer;

use std::path::PathBuf;

pub use response_cache::{CacheStats, McSettings, ResponseCache};
pub use simulation::{
    NoProgress, Progress, SimulationOptions, SimulationReport, scaled_booth, simulate_calibration,
    simulate_scan,
};
pub use skin_optics::SkinPreset;
pub use subjects::SubjectKind;

/// Errors of the virtual booth.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VirtualBoothError {
    /// Writing the capture folder failed.
    #[error(transparent)]
    Capture(#[from] mlsss_core::capture::CaptureError),
    /// Writing a truth image failed.
    #[error(transparent)]
    Image(#[from] mlsss_core::imageio::ImageIoError),
    /// Writing the true calibration failed.
    #[error(transparent)]
    Calibration(#[from] mlsss_core::calibration::CalibrationError),
    /// The Monte Carlo simulation rejected its input.
    #[error("Monte Carlo: {0}")]
    Mc(#[from] mlsss_mc::McError),
    /// The response cache could not be read or written.
    #[error("response cache {path}: {source} (set MLSSS_CACHE to a writable directory)")]
    Cache {
        path: PathBuf,
        source: std::io::Error,
    },
    /// A truth file could not be written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// JSON serialisation failed.
    #[error("JSON: {0}")]
    Json(serde_json::Error),
    /// An option does not fit the request.
    #[error("invalid --{option}: {reason}")]
    InvalidOption {
        option: &'static str,
        reason: String,
    },
    /// The camera does not see the subject at all.
    #[error("the camera sees nothing of the subject: check the booth geometry")]
    EmptyView,
    /// A broken internal invariant (a bug).
    #[error("internal error: {0}")]
    Internal(&'static str),
}
