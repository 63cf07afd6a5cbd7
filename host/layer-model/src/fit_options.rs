//! The knobs of the fit stage ([`super::fit`]), shared with the layer spacing estimate
//! ([`super::layer_depth`]) that the fit runs first.

use super::mixture::EmConfig;

/// EM variant of DESIGN section 5.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EmVariant {
    /// Means tied to layer depth, joint over projectors and axes (ours).
    #[default]
    Layered,
    /// Free means per profile, averaged (the paper).
    Free,
}

/// Knobs of the fit stage.
#[derive(Debug, Clone, PartialEq)]
pub struct FitOptions {
    pub em: EmConfig,
    pub variant: EmVariant,
    /// Fixed layer spacing (mm); `None` estimates it.
    pub depth_spacing: Option<f64>,
    /// Start and upper bound of the spacing estimate (mm; `subsurface::layer_depth`).
    pub spacing_start: f64,
    pub spacing_max: f64,
    /// Pixels used for the spacing estimate (each with all 3 channels).
    pub spacing_pixels: usize,
    /// Fit one pixel per `block x block` tile.
    pub block: usize,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            em: EmConfig::default(),
            variant: EmVariant::Layered,
            depth_spacing: None,
            spacing_start: 0.1,
            spacing_max: 1.0,
            spacing_pixels: 64,
            block: 1,
        }
    }
}
