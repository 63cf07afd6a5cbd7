//! Spatial prior on the fitted layer model: each pixel's layer shape and amplitude are pulled
//! toward its neighbourhood as far as the training data say they should be.
//!
//! Why: a pixel's layers come from its own few profiles (the shape from one tile's EM fit, the
//! amplitude from the pixel's own flux). Both carry errors that do not transfer to a new light:
//! camera noise and the per-projector error of the irradiance model. On the quick head the raw
//! per-pixel model lost to the homogeneous one under white light (held-out global error 0.100 vs
//! 0.090): the inhomogeneity it captured was outweighed by its noise. Skin's parameters vary
//! smoothly over most of the face, so borrowing strength from neighbours is the usual cure; the
//! two strengths below are chosen from the training data alone (never the held-out projector).
//!
//! - **Shape** (weights relative to their sum, sigmas, depths): the shape of a tile becomes the
//!   equal-weight mixture of the shapes of the fitted tiles within Chebyshev radius `r` (tiles of
//!   the fit's `block`), with components merged within log-sigma bins (variance moment-matched,
//!   depth weight-averaged) so the layer count stays small. `r` is chosen per channel among
//!   [`PriorOptions::radii`] and "global" (one shape for the whole subject) by cross-validation:
//!   the log-likelihood of the profiles of validation pixels that no fit used (per tile, a lit
//!   pixel other than the fitted one; with `block = 1` the right neighbour, whose own tile is then
//!   left out of the mixture).
//! - **Amplitude** (the sum of a pixel's layer weights): empirical Bayes shrinkage toward the
//!   subject's mean `m`. Each training projector `p` gives its own estimate `a_p = F_p / (E_p W_p)`
//!   (flux of its two profiles over irradiance times slit width); their spread within a pixel is
//!   the noise variance `s2`, the spread of pixel means beyond what that noise explains is the true
//!   variation `t2`. A pixel seen by `n` projectors keeps the fraction `n / (n + kappa)` of its
//!   deviation from `m` (the posterior mean under a Gaussian prior, in relative units). `kappa`
//!   is chosen by leave-one-projector-out prediction of each projector's estimate from the
//!   pixel's others (`amplitude::loo_kappa`); the moment estimate `kappa = s2 / t2` (reported as well)
//!   assumes the projectors' errors independent, and on the quick head with the estimated
//!   calibration they are not: it kept 80-95 % of the deviations where prediction says ~50 %.
//!
//! Pixels without layers stay without layers; the output has the input's size.

mod amplitude;
mod cross_validation;
mod shapes;
mod tiles;

#[cfg(test)]
mod tests;

use std::collections::BTreeMap;

use rayon::prelude::*;
use serde::Serialize;

use crate::mixture::EmError;
use crate::profiles::{GeometryMap, SlitSweep};
use crate::render::{LayerModel, RowSource, ShapeLayer};
use crate::surface::Surface;
use amplitude::{AmplitudeStats, Amplitudes};
use cross_validation::{Choice, choose_neighbourhoods};
use shapes::{Shape, merged_mixture, without_faint};
use tiles::{Inputs, Tiles, hood_shape};

/// Errors of the spatial prior.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum SpatialPriorError {
    /// The per-projector inputs disagree in number.
    #[error("{geometries} projector geometries but {sweeps} slit sweeps")]
    ProjectorCount { geometries: usize, sweeps: usize },
    /// The layer model and the surface differ in size.
    #[error("layer model is {model_width}x{model_height}, the surface {width}x{height}")]
    SizeMismatch {
        model_width: usize,
        model_height: usize,
        width: usize,
        height: usize,
    },
    /// An option is out of range.
    #[error("invalid spatial prior option: {0}")]
    BadOption(&'static str),
    /// A likelihood evaluation failed on malformed profiles.
    #[error("validation pixel {pixel}: {source}")]
    Likelihood { pixel: usize, source: EmError },
}

/// Knobs of the prior.
#[derive(Debug, Clone, PartialEq)]
pub struct PriorOptions {
    /// Candidate shape radii in tiles (0 = the tile's own shape); "global" is always a candidate.
    pub radii: Vec<usize>,
    /// Ratio between consecutive sigma bins when merging components (> 1).
    pub sigma_bin_ratio: f64,
    /// Shrink the amplitudes (empirical Bayes); off keeps each pixel's own.
    pub shrink_amplitude: bool,
    /// Slit images on each side in the likelihood (as the EM's `wrap_images`).
    pub wrap_images: usize,
    /// At most about this many tiles, evenly spread, have their validation pixel's likelihood
    /// scored (the report's `cv_log_likelihood` is a mean over tiles; the choice rests on the
    /// width prediction, which scores every tile). Why: scoring every tile of a full-size capture
    /// under every candidate cost more CPU than the EM fits themselves (60 of ~200 CPU-s). 1024
    /// (4096 before): the full-size head's 1875 validation pixels per channel were still ~0.9
    /// CPU-s, a fifth of the prior and the dipole baseline together, for a report figure the
    /// choice does not use where the widths can be scored; about 480 give its mean now.
    pub likelihood_tiles: usize,
}

impl Default for PriorOptions {
    fn default() -> Self {
        Self {
            radii: vec![0, 1, 2, 3, 4],
            sigma_bin_ratio: 1.25,
            shrink_amplitude: true,
            wrap_images: 1,
            likelihood_tiles: 1024,
        }
    }
}

/// Candidate shape neighbourhood.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Neighbourhood {
    /// Tiles within this Chebyshev radius (in tiles).
    Radius(usize),
    /// Every fitted tile of the subject.
    Global,
}

impl Neighbourhood {
    /// Label for reports: `r0`, `r1`, ..., `global`.
    pub fn label(self) -> String {
        match self {
            Self::Radius(r) => format!("r{r}"),
            Self::Global => "global".into(),
        }
    }
}

/// What the prior chose for one channel, and why.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChannelPrior {
    /// Chosen shape neighbourhood (label, e.g. `r2` or `global`).
    pub shape: String,
    /// Mean held-out log-likelihood per validation profile set, per candidate label (over the
    /// tiles [`PriorOptions::likelihood_tiles`] selects).
    pub cv_log_likelihood: BTreeMap<String, f64>,
    /// Leave-one-projector-out mean squared error of the validation pixels' log profile width
    /// per candidate label (the criterion of the choice, with the one-standard-error rule).
    pub width_loo_mse: BTreeMap<String, f64>,
    /// Subject mean amplitude `m`.
    pub amplitude_mean: f64,
    /// Relative noise variance of one projector's amplitude estimate (`s2`).
    pub noise_variance: f64,
    /// Relative variance of the true amplitudes (`t2`).
    pub signal_variance: f64,
    /// Amplitude prior strength chosen by leave-one-projector-out prediction (a pixel seen by
    /// `n` projectors keeps `n / (n + kappa)`; `None`: too few projectors, the moment estimate
    /// `t2 / (t2 + s2 / n)` is used), and its mean squared relative prediction error.
    pub amplitude_kappa: Option<f64>,
    pub amplitude_cv_mse: Option<f64>,
    /// Mean fraction of each pixel's deviation kept (1 = no shrinkage).
    pub mean_keep_fraction: f64,
}

/// What the prior did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PriorReport {
    /// Validation pixels whose likelihood was scored per channel (at most about
    /// [`PriorOptions::likelihood_tiles`]).
    pub validation_pixels: [usize; 3],
    /// R, G, B.
    pub channels: Vec<ChannelPrior>,
}

/// The pipeline's call: with `enabled`, replaces `model` by its regularised version (default
/// options) and reports what was chosen; otherwise leaves it alone and returns `None`.
#[allow(clippy::too_many_arguments)]
pub fn regularise_in_place(
    enabled: bool,
    model: &mut LayerModel,
    surface: &Surface,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    block: usize,
    depth_spacing: f64,
) -> Result<Option<PriorReport>, SpatialPriorError> {
    if !enabled {
        return Ok(None);
    }
    let opts = PriorOptions::default();
    let (out, report) = regularise(
        model,
        surface,
        geometries,
        sweeps,
        block,
        depth_spacing,
        &opts,
    )?;
    *model = out;
    Ok(Some(report))
}

/// Applies the prior to the fitted `model` (layers per pixel as `subsurface::fit::fit_model`
/// returns them, fitted per `block x block` tile, layer depth `depth_index * depth_spacing`).
pub fn regularise(
    model: &LayerModel,
    surface: &Surface,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    block: usize,
    depth_spacing: f64,
    opts: &PriorOptions,
) -> Result<(LayerModel, PriorReport), SpatialPriorError> {
    check_inputs(model, surface, geometries, sweeps, opts)?;
    let inputs = Inputs {
        model,
        surface,
        geometries,
        sweeps,
        tiles: Tiles::new(surface.width, surface.height, block),
        depth_spacing,
        opts,
    };
    let shapes = inputs.tile_shapes();
    let global: [Option<Shape>; 3] = std::array::from_fn(|c| {
        merged_mixture(
            shapes.iter().filter_map(|s| s[c].as_ref()),
            opts.sigma_bin_ratio,
        )
    });
    let mut candidates: Vec<Neighbourhood> = opts
        .radii
        .iter()
        .map(|&r| Neighbourhood::Radius(r))
        .collect();
    candidates.push(Neighbourhood::Global);
    let choice = choose_neighbourhoods(&inputs, &shapes, &global, &candidates)?;
    // Amplitudes: the fit's own per pixel, and per projector for the variance components.
    let amplitudes = Amplitudes::measure(model, surface.len(), geometries, sweeps);
    let prior = Prior {
        shapes: chosen_shapes(&inputs, &shapes, &global, &choice.chosen),
        amplitudes: &amplitudes,
        tiles: inputs.tiles,
        shrink_amplitude: opts.shrink_amplitude,
    };
    let out = prior.apply(model, surface);
    Ok((out, prior.report(&choice)))
}

/// The inputs agree in size and the options are in range.
fn check_inputs(
    model: &LayerModel,
    surface: &Surface,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    opts: &PriorOptions,
) -> Result<(), SpatialPriorError> {
    if geometries.len() != sweeps.len() {
        return Err(SpatialPriorError::ProjectorCount {
            geometries: geometries.len(),
            sweeps: sweeps.len(),
        });
    }
    if (model.width, model.height) != (surface.width, surface.height)
        || geometries.iter().any(|g| g.len() != surface.len())
    {
        return Err(SpatialPriorError::SizeMismatch {
            model_width: model.width,
            model_height: model.height,
            width: surface.width,
            height: surface.height,
        });
    }
    if opts.sigma_bin_ratio.is_nan() || opts.sigma_bin_ratio <= 1.0 {
        return Err(SpatialPriorError::BadOption("sigma_bin_ratio must be > 1"));
    }
    Ok(())
}

/// Shapes of every tile under the chosen neighbourhoods, without the layers the renderer skips
/// by default.
fn chosen_shapes(
    inputs: &Inputs,
    shapes: &[[Option<Shape>; 3]],
    global: &[Option<Shape>; 3],
    chosen: &[Neighbourhood; 3],
) -> Vec<[Option<Shape>; 3]> {
    (0..inputs.tiles.count())
        .into_par_iter()
        .map(|t| {
            std::array::from_fn(|c| {
                hood_shape(inputs, shapes, global, t, c, chosen[c], None).map(without_faint)
            })
        })
        .collect()
}

/// The prior as chosen: every tile's shape per channel, and the amplitudes it shrinks.
struct Prior<'a> {
    shapes: Vec<[Option<Shape>; 3]>,
    amplitudes: &'a Amplitudes,
    tiles: Tiles,
    shrink_amplitude: bool,
}

impl Prior<'_> {
    /// The tile whose shape the prior gives pixel `i` in channel `c`, and the fraction of the
    /// amplitude's deviation kept, where both apply.
    fn of(&self, i: usize, c: usize) -> Option<(usize, Option<f64>)> {
        let a = self.amplitudes;
        if a.own[i][c] <= 0.0 {
            return None;
        }
        let tile = self.tiles.of_pixel(i);
        // Only where the tile has a shape in this channel.
        self.shapes[tile][c].as_ref()?;
        let st = &a.stats[c];
        let keep = (self.shrink_amplitude && st.mean > 0.0)
            .then(|| st.keep(a.per_projector.get(i, c).len()));
        Some((tile, keep))
    }

    /// `model` with the prior's shape and shrunk amplitude wherever both apply: those rows
    /// share their tile's shape, scaled by the pixel's amplitude.
    fn apply(&self, model: &LayerModel, surface: &Surface) -> LayerModel {
        LayerModel::from_shapes(
            surface.width,
            surface.height,
            |i, c| match self.of(i, c) {
                None => RowSource::Own(model.layers(i, c)),
                Some((tile, keep)) => {
                    let (amplitude, mean) =
                        (self.amplitudes.own[i][c], self.amplitudes.stats[c].mean);
                    let target =
                        keep.map_or(amplitude, |k| mean * (1.0 + k * (amplitude / mean - 1.0)));
                    RowSource::Shape {
                        key: (tile, c),
                        scale: target,
                    }
                }
            },
            |(t, c)| self.shapes[t][c].iter().flatten().map(ShapeLayer::from),
        )
    }

    /// Mean fraction of each pixel's deviation kept in channel `c` (1 without shrinkage).
    fn mean_keep_fraction(&self, c: usize) -> f64 {
        let keeps: Vec<f64> = (0..self.amplitudes.own.len())
            .filter_map(|i| self.of(i, c)?.1)
            .collect();
        if keeps.is_empty() {
            1.0
        } else {
            keeps.iter().sum::<f64>() / keeps.len() as f64
        }
    }

    /// What was chosen and why, per channel.
    fn report(&self, choice: &Choice) -> PriorReport {
        let channels = (0..3)
            .map(|c| {
                let stats: &AmplitudeStats = &self.amplitudes.stats[c];
                ChannelPrior {
                    shape: choice.chosen[c].label(),
                    cv_log_likelihood: choice.tables[c].clone(),
                    width_loo_mse: choice.width_tables[c].clone(),
                    amplitude_mean: stats.mean,
                    noise_variance: stats.noise,
                    signal_variance: stats.signal,
                    amplitude_kappa: stats.kappa,
                    amplitude_cv_mse: stats.cv_mse,
                    mean_keep_fraction: self.mean_keep_fraction(c),
                }
            })
            .collect();
        PriorReport {
            validation_pixels: choice.counts,
            channels,
        }
    }
}
