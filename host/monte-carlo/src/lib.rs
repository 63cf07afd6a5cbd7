//! Monte Carlo light transport in a planar multi-layer medium, with the physics of MCML
//! (Wang, Jacques & Zheng 1995, "MCML — Monte Carlo modeling of light transport in multi-layered
//! tissues"): Henyey-Greenstein scattering, absorption by weight, Russian roulette, Fresnel
//! reflection and refraction at every boundary whose refractive indices differ (including the
//! internal interfaces between layers), an ambient medium above and below, and a pencil beam at any
//! angle of incidence.
//!
//! This is the ground truth of the virtual booth: it knows nothing of the MLSSS Gaussian model.
//!
//! The same random lanes and fast maths also give standard normal deviates in bulk (`NormalStream`,
//! Box-Muller in f32), which the virtual booth draws its camera noise from.
//!
//! Conventions
//! - Units: lengths in mm, coefficients in 1/mm, angles in degrees at the API.
//! - Frame: the surface is the plane z = 0 and z grows INTO the medium. Layer 0 is the top layer.
//! - The beam hits the surface at the origin. Its plane of incidence is the x-z plane and it comes
//!   from the -x side, so the refracted ray travels towards +x: x points AWAY from the light and
//!   forward scattering shows up at positive x. y completes a right-handed frame with x and z.
//! - Every tally is per incident photon (each photon is launched with weight 1). Exit responses
//!   are per unit area (1/mm² per incident photon).
//! - `specular` is the Fresnel reflection of the beam at the entry surface only; everything that
//!   leaves the top after entering the medium is diffuse reflectance (as in MCML).
//! - Results depend only on the medium, the configuration and the seed, never on the number of
//!   threads: photons are simulated in fixed batches, each with its own random stream, and the
//!   batch tallies are summed in batch order. Within a batch, `GROUPS` x `LANES` photons are in flight
//!   at once (SIMD over photons, see `photon_lanes`), each lane with its own random stream.

mod fast_math;
mod fresnel;
mod gaussian;
mod lane_rng;
mod layers_file;
mod medium;
mod photon_lanes;
mod simd;
#[cfg(target_arch = "x86_64")]
mod simd_avx2;
#[cfg(target_arch = "x86_64")]
mod simd_avx512;
mod tally;
mod transport;

use std::path::PathBuf;

pub use fresnel::{fresnel_reflectance, refracted_cos};
pub use gaussian::NormalStream;
pub use layers_file::LayersFile;
pub use medium::{Layer, MAX_COEFFICIENT_PER_MM, Medium};
pub use tally::{ExitResponse2D, GridSpec, RadialProfile, RadialSpec};

/// Names the random streams and the order in which photons draw from them (`LANES` photons in
/// flight per batch, xoshiro128++ per lane). The result for a given (medium, config) is fixed
/// while this stays the same and changes, within the noise, when it does: caches of Monte Carlo
/// results must include it in their key.
pub const RANDOM_STREAMS: &str =
    "xoshiro128++, 3 groups x 16 lanes of 4096-photon batches, f32 lanes, v4";

/// Errors of the Monte Carlo module.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum McError {
    /// The medium has no layer.
    #[error("the medium has no layer: give at least one")]
    NoLayers,
    /// A layer parameter is out of its physical range.
    #[error("layer {index}: invalid `{field}` = {value:?}: {reason}")]
    InvalidLayer {
        index: usize,
        field: &'static str,
        value: f64,
        reason: &'static str,
    },
    /// A parameter of the medium (ambient indices) is out of range.
    #[error("invalid medium `{field}` = {value}: {reason}")]
    InvalidMedium {
        field: &'static str,
        value: f64,
        reason: &'static str,
    },
    /// A run parameter is out of range.
    #[error("invalid Monte Carlo setting `{field}` = {value}: {reason}")]
    InvalidConfig {
        field: &'static str,
        value: f64,
        reason: &'static str,
    },
    /// A layers file could not be read.
    #[error("cannot read layers file {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// A layers file is not valid TOML for the layers format.
    #[error("{path}:{line}:{column}: {message}")]
    Parse {
        path: PathBuf,
        line: usize,
        column: usize,
        message: String,
    },
}

/// How to run the simulation.
#[derive(Debug, Clone, PartialEq)]
pub struct McConfig {
    /// Number of photons launched.
    pub photons: u64,
    /// Seed of the random streams; the result is a pure function of (medium, config).
    pub seed: u64,
    /// Angle of incidence of the pencil beam in the ambient medium above, degrees from the normal,
    /// in [0, 90).
    pub incidence_deg: f64,
    /// Tabulate the diffuse exit weight on a 2-D grid in the surface plane.
    pub grid: Option<GridSpec>,
    /// Tabulate the diffuse exit weight in rings around the entry point.
    pub radial: Option<RadialSpec>,
}

impl McConfig {
    /// Normal incidence, no spatial tallies.
    pub fn new(photons: u64, seed: u64) -> Self {
        Self {
            photons,
            seed,
            incidence_deg: 0.0,
            grid: None,
            radial: None,
        }
    }
}

/// What a run measured. Fractions are of the incident power; `_se` fields are one standard error
/// (from the per-photon variance of the tally).
#[derive(Debug, Clone, PartialEq)]
pub struct McResult {
    /// Fresnel reflection of the beam at the entry surface (exact, no noise).
    pub specular: f64,
    /// Light leaving the top surface after entering the medium.
    pub diffuse_reflectance: f64,
    /// Standard error of `diffuse_reflectance`.
    pub diffuse_reflectance_se: f64,
    /// Light leaving the bottom surface (scattered and unscattered); 0 for a semi-infinite medium.
    pub total_transmittance: f64,
    /// Standard error of `total_transmittance`.
    pub total_transmittance_se: f64,
    /// Fraction absorbed in each layer, top first.
    pub absorbed: Vec<f64>,
    /// Standard error of each entry of `absorbed`.
    pub absorbed_se: Vec<f64>,
    /// Weight-averaged exit point (x, y) of the diffuse reflectance, mm; unbinned.
    pub exit_centroid_mm: [f64; 2],
    /// Photons launched.
    pub photons: u64,
    /// Wall-clock throughput of this run (all threads together).
    pub photons_per_second: f64,
    /// Wall-clock interaction (absorption + scattering) events per second, all threads together:
    /// the throughput figure that does not depend on how long photons live in the medium.
    pub interactions_per_second: f64,
    /// Worker threads used (does not change the result).
    pub threads: usize,
    /// Instruction set the photon lanes ran on ("avx512", "avx2" or "baseline"); every choice
    /// gives bit-identical results.
    pub simd: &'static str,
    /// Mean number of interaction (absorption + scattering) events per photon: the cost driver.
    pub interactions_per_photon: f64,
    /// The 2-D exit response, when `McConfig::grid` was given.
    pub response: Option<ExitResponse2D>,
    /// The radial profile R(r), when `McConfig::radial` was given.
    pub radial: Option<RadialProfile>,
}

/// Simulates `cfg.photons` photons in `medium` and returns the tallies.
pub fn run(medium: &Medium, cfg: &McConfig) -> Result<McResult, McError> {
    medium.validate()?;
    validate_config(cfg)?;
    Ok(transport::simulate(medium, cfg))
}

fn validate_config(cfg: &McConfig) -> Result<(), McError> {
    let invalid = |field, value: f64, reason| McError::InvalidConfig {
        field,
        value,
        reason,
    };
    if cfg.photons == 0 {
        return Err(invalid("photons", 0.0, "launch at least one photon"));
    }
    if !(0.0..90.0).contains(&cfg.incidence_deg) {
        return Err(invalid(
            "incidence_deg",
            cfg.incidence_deg,
            "must be in [0, 90) degrees",
        ));
    }
    if let Some(grid) = &cfg.grid {
        grid.validate()?;
    }
    if let Some(radial) = &cfg.radial {
        radial.validate()?;
    }
    Ok(())
}
