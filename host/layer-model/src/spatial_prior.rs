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
//!   pixel's others ([`loo_kappa`]); the moment estimate `kappa = s2 / t2` (reported as well)
//!   assumes the projectors' errors independent, and on the quick head with the estimated
//!   calibration they are not: it kept 80-95 % of the deviations where prediction says ~50 %.
//!
//! Pixels without layers stay without layers; the output has the input's size.

use std::collections::BTreeMap;

use rayon::prelude::*;
use serde::Serialize;

use super::em_layered::{self, Layer, LayeredParams};
use super::fit::tile_pixel;
use super::mixture::{EmError, Profile};
use super::profiles::{PixelGeometry, SlitSweep};
use super::render::{LayerModel, RenderOptions, SplatLayer};
use super::surface::Surface;

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
    /// under every candidate cost more CPU than the EM fits themselves (60 of ~200 CPU-s).
    pub likelihood_tiles: usize,
}

impl Default for PriorOptions {
    fn default() -> Self {
        Self {
            radii: vec![0, 1, 2, 3, 4],
            sigma_bin_ratio: 1.25,
            shrink_amplitude: true,
            wrap_images: 1,
            likelihood_tiles: 4096,
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

/// A layer shape: weights sum to 1.
type Shape = Vec<SplatLayer>;

/// The tile grid of a fit with `block x block` tiles.
#[derive(Debug, Clone, Copy)]
struct Tiles {
    width: usize,
    height: usize,
    block: usize,
    across: usize,
    down: usize,
}

impl Tiles {
    fn new(width: usize, height: usize, block: usize) -> Self {
        let block = block.max(1);
        Self {
            width,
            height,
            block,
            across: width.div_ceil(block),
            down: height.div_ceil(block),
        }
    }

    fn count(&self) -> usize {
        self.across * self.down
    }

    fn of_pixel(&self, i: usize) -> usize {
        (i / self.width / self.block) * self.across + (i % self.width) / self.block
    }
}

/// The pixel's layers scaled to unit total weight; `None` without weight.
fn normalised(layers: &[SplatLayer]) -> Option<Shape> {
    let total: f32 = layers.iter().map(|l| l.weight).sum();
    (total > 0.0 && total.is_finite()).then(|| {
        layers
            .iter()
            .map(|l| SplatLayer {
                weight: l.weight / total,
                ..*l
            })
            .collect()
    })
}

/// Sigma bins per layer index in the merged layers' `index` code (`index * SIGMA_BINS + bin`).
const SIGMA_BINS: u16 = 64;

/// The merged layers' identity: depth index (or rank) and sigma bin, so that layers averaged
/// across pixels by index (the homogeneous baseline) share depth and width.
fn layer_code(index: u16, bin: i32) -> u16 {
    let bin = (bin + i32::from(SIGMA_BINS / 2)).clamp(0, i32::from(SIGMA_BINS) - 1) as u16;
    index.saturating_mul(SIGMA_BINS).saturating_add(bin)
}

/// The layer index layers are merged under: one family for every depth. Layers of one sigma
/// bin at different depths merge into one at their weight-averaged depth, which keeps the first
/// moment of the shifted light (linear in depth) for every light direction; the spread of
/// shifts lost, `(z_max - z_min) |t_i|` (0.3 mm x 0.64 on the quick demo), matters only where
/// sigma is as small, below the camera pixel. Keeping the depths apart multiplies the layer
/// count by the depth indices as soon as `D > 0` (quick demo: model 76 -> 183 MB, held-out
/// render time x2.4; `subsurface::layer_depth`).
fn depth_key(_l: &SplatLayer) -> u16 {
    0
}

/// Equal-weight mixture of `shapes`, components of one family ([`depth_key`]) merged within log-sigma bins
/// (weight summed, variance moment-matched, depth weight-averaged); the merged layers' `index`
/// is [`layer_code`].
fn merged_mixture<'a>(shapes: impl Iterator<Item = &'a Shape>, bin_ratio: f64) -> Option<Shape> {
    // (layer index, sigma bin) -> (weight, weight * sigma^2, weight * depth)
    let mut bins: BTreeMap<(u16, i32), (f64, f64, f64)> = BTreeMap::new();
    let mut count = 0usize;
    let log_ratio = bin_ratio.ln();
    for shape in shapes {
        count += 1;
        for l in shape {
            let sigma = f64::from(l.sigma_mm).max(1e-6);
            let bin = (sigma.ln() / log_ratio).round() as i32;
            let e = bins.entry((depth_key(l), bin)).or_insert((0.0, 0.0, 0.0));
            let w = f64::from(l.weight);
            e.0 += w;
            e.1 += w * sigma * sigma;
            e.2 += w * f64::from(l.depth_mm);
        }
    }
    if count == 0 {
        return None;
    }
    let out: Shape = bins
        .iter()
        .filter(|(_, e)| e.0 > 0.0)
        .map(|(&(index, bin), &(w, wss, wd))| SplatLayer {
            index: layer_code(index, bin),
            weight: (w / count as f64) as f32,
            sigma_mm: (wss / w).sqrt() as f32,
            depth_mm: (wd / w) as f32,
        })
        .collect();
    (!out.is_empty()).then_some(out)
}

/// `shape` without the layers whose weight is at most the renderer's default
/// `min_relative_weight` of the total, which it skips: merged shapes carry many such (the
/// full-size subject's global shape: 9-14 of 25-29 layers per channel), and storing them made
/// the model ~1.8x larger and every pass over it slower for no change in a default render. The
/// rest keep their weights (the renderer does not renormalise either), so default renders are
/// unchanged: dropping layers only raises the others' share of the smaller total.
fn without_faint(mut shape: Shape) -> Shape {
    let floor = RenderOptions::default().min_relative_weight;
    let total: f32 = shape.iter().map(|l| l.weight).sum();
    shape.retain(|l| l.weight > floor * total);
    shape
}

/// Profiles of pixel `i`, channel `c`, grouped per training projector that lights it, with each
/// group's `E W` (irradiance x slit width summed over its profiles).
fn profiles_by_projector(
    i: usize,
    c: usize,
    geometries: &[Vec<Option<PixelGeometry>>],
    sweeps: &[SlitSweep],
) -> Vec<(Vec<Profile>, f64)> {
    geometries
        .iter()
        .zip(sweeps)
        .filter_map(|(geo, sweep)| {
            let g = geo.get(i).copied().flatten()?;
            let profiles: Vec<Profile> =
                (0..2).filter_map(|a| sweep.profile(i, c, a, &g)).collect();
            let ew: f64 = profiles.iter().map(|p| g.irradiance * p.slit_width).sum();
            (!profiles.is_empty()).then_some((profiles, ew))
        })
        .collect()
}

/// Pixel `i`'s amplitude in channel `c` as each training projector that lights it measures it
/// (its profiles' flux over their `E W`): the same numbers as [`profiles_by_projector`]'s
/// groups give, without building the profiles.
fn projector_amplitudes(
    i: usize,
    c: usize,
    geometries: &[Vec<Option<PixelGeometry>>],
    sweeps: &[SlitSweep],
) -> Vec<f64> {
    geometries
        .iter()
        .zip(sweeps)
        .filter_map(|(geo, sweep)| {
            let g = geo.get(i).copied().flatten()?;
            let (mut flux, mut ew, mut any) = (0.0, 0.0, false);
            for (f, e) in sweep.fluxes(i, c, &g) {
                flux += f;
                ew += e;
                any = true;
            }
            (any && ew > 0.0).then(|| flux / ew)
        })
        .collect()
}

/// Log-likelihood (per unit weight, averaged over profiles) of `profiles` under `shape`, each
/// layer at its own depth in units of `depth_spacing` (depth ignored when the spacing is 0, as
/// the layered fit's means are then all 0).
fn shape_log_likelihood(
    profiles: &[Profile],
    shape: &Shape,
    depth_spacing: f64,
    wrap_images: usize,
) -> Result<f64, EmError> {
    let params = LayeredParams {
        layers: shape
            .iter()
            .map(|l| Layer {
                depth_index: if depth_spacing > 0.0 {
                    (f64::from(l.depth_mm) / depth_spacing).round().max(0.0) as usize
                } else {
                    0
                },
                weight: f64::from(l.weight),
                sigma: f64::from(l.sigma_mm),
            })
            .collect(),
        depth_spacing,
    };
    em_layered::log_likelihood(profiles, &params, wrap_images)
}

/// Everything the prior needs, borrowed.
struct Inputs<'a> {
    model: &'a LayerModel,
    surface: &'a Surface,
    geometries: &'a [Vec<Option<PixelGeometry>>],
    sweeps: &'a [SlitSweep<'a>],
    tiles: Tiles,
    depth_spacing: f64,
    opts: &'a PriorOptions,
}

impl Inputs<'_> {
    fn lit(&self, i: usize) -> bool {
        self.surface.mask[i] && self.geometries.iter().any(|g| g[i].is_some())
    }

    /// The pixel the fit used for tile `t`.
    fn fitted_pixel(&self, t: usize) -> Option<usize> {
        let tl = &self.tiles;
        tile_pixel(
            t % tl.across,
            t / tl.across,
            tl.block,
            tl.width,
            tl.height,
            &|i| self.lit(i),
        )
    }

    /// Shape of every tile and channel (from the fitted pixel's layers).
    fn tile_shapes(&self) -> Vec<[Option<Shape>; 3]> {
        (0..self.tiles.count())
            .into_par_iter()
            .map(|t| {
                let mut out: [Option<Shape>; 3] = Default::default();
                if let Some(i) = self.fitted_pixel(t) {
                    for (c, o) in out.iter_mut().enumerate() {
                        *o = normalised(self.model.layers(i, c));
                    }
                }
                out
            })
            .collect()
    }

    /// A pixel of tile `t` no fit used, and the tile to leave out of its mixtures (the tile the
    /// validation pixel was fitted in, when that is not `t`).
    fn validation_pixel(&self, t: usize) -> Option<(usize, Option<usize>)> {
        let tl = &self.tiles;
        let fitted = self.fitted_pixel(t)?;
        if tl.block == 1 {
            let x = fitted % tl.width;
            let right = fitted + 1;
            return (x + 1 < tl.width && self.lit(right)).then_some((right, Some(right)));
        }
        let (x0, y0) = ((t % tl.across) * tl.block, (t / tl.across) * tl.block);
        let (x1, y1) = (
            (x0 + tl.block).min(tl.width),
            (y0 + tl.block).min(tl.height),
        );
        (y0..y1)
            .rev()
            .flat_map(|y| (x0..x1).rev().map(move |x| y * tl.width + x))
            .find(|&i| i != fitted && self.lit(i))
            .map(|i| (i, None))
    }

    /// Tiles within Chebyshev radius `r` of tile `t` (itself included).
    fn window(&self, t: usize, r: usize) -> impl Iterator<Item = usize> + '_ {
        let tl = self.tiles;
        let (tx, ty) = (t % tl.across, t / tl.across);
        let (x0, x1) = (tx.saturating_sub(r), (tx + r).min(tl.across - 1));
        let (y0, y1) = (ty.saturating_sub(r), (ty + r).min(tl.down - 1));
        (y0..=y1).flat_map(move |y| (x0..=x1).map(move |x| y * tl.across + x))
    }
}

/// The mixture shape of tile `t` over `hood`, leaving out tile `exclude`.
fn hood_shape(
    inputs: &Inputs,
    shapes: &[[Option<Shape>; 3]],
    global: &[Option<Shape>; 3],
    t: usize,
    c: usize,
    hood: Neighbourhood,
    exclude: Option<usize>,
) -> Option<Shape> {
    match hood {
        Neighbourhood::Global => global[c].clone(),
        Neighbourhood::Radius(r) => merged_mixture(
            inputs
                .window(t, r)
                .filter(|&s| Some(s) != exclude)
                .filter_map(|s| shapes[s][c].as_ref()),
            inputs.opts.sigma_bin_ratio,
        ),
    }
}

/// The cross-validation's outcome per channel: the chosen neighbourhood, the mean log-likelihood
/// per candidate label, and the number of validation pixels scored.
struct Choice {
    chosen: [Neighbourhood; 3],
    tables: [BTreeMap<String, f64>; 3],
    /// Leave-one-projector-out mean squared error of the log width per candidate label.
    width_tables: [BTreeMap<String, f64>; 3],
    counts: [usize; 3],
}

/// Chooses the shape neighbourhood of each channel by the validation pixels' log-likelihood.
fn choose_neighbourhoods(
    inputs: &Inputs,
    shapes: &[[Option<Shape>; 3]],
    global: &[Option<Shape>; 3],
    candidates: &[Neighbourhood],
) -> Result<Choice, SpatialPriorError> {
    // Per tile and channel: the log-likelihood under every candidate (None when not scorable).
    type Scores = [Option<Vec<f64>>; 3];
    let stride = inputs
        .tiles
        .count()
        .div_ceil(inputs.opts.likelihood_tiles.max(1))
        .max(1);
    let per_tile: Vec<Result<Scores, SpatialPriorError>> = (0..inputs.tiles.count())
        .into_par_iter()
        .step_by(stride)
        .map(|t| {
            let mut out: Scores = Default::default();
            let Some((v, exclude)) = inputs.validation_pixel(t) else {
                return Ok(out);
            };
            for (c, o) in out.iter_mut().enumerate() {
                let profiles: Vec<Profile> =
                    profiles_by_projector(v, c, inputs.geometries, inputs.sweeps)
                        .into_iter()
                        .flat_map(|(p, _)| p)
                        .collect();
                if profiles.iter().all(|p| p.total() <= 0.0) {
                    continue;
                }
                let mut scores = Vec::with_capacity(candidates.len());
                for &hood in candidates {
                    let Some(shape) = hood_shape(inputs, shapes, global, t, c, hood, exclude)
                    else {
                        break;
                    };
                    match shape_log_likelihood(
                        &profiles,
                        &shape,
                        inputs.depth_spacing,
                        inputs.opts.wrap_images,
                    ) {
                        Ok(ll) if ll.is_finite() => scores.push(ll),
                        Ok(_) | Err(EmError::NoSignal) => break,
                        Err(source) => {
                            return Err(SpatialPriorError::Likelihood { pixel: v, source });
                        }
                    }
                }
                // Score a tile only when every candidate could be evaluated (a fair comparison).
                if scores.len() == candidates.len() {
                    *o = Some(scores);
                }
            }
            Ok(out)
        })
        .collect();
    let mut scores: [Vec<Vec<f64>>; 3] = Default::default();
    for tile in per_tile {
        for (c, s) in tile?.into_iter().enumerate() {
            if let Some(s) = s {
                scores[c].push(s);
            }
        }
    }
    let counts = [scores[0].len(), scores[1].len(), scores[2].len()];
    let width = width_loo_scores(inputs, candidates);
    let mut width_tables: [BTreeMap<String, f64>; 3] = Default::default();
    let mut chosen = [Neighbourhood::Radius(0); 3];
    let mut tables: [BTreeMap<String, f64>; 3] = Default::default();
    for c in 0..3 {
        if counts[c] == 0 {
            continue;
        }
        let means: Vec<f64> = (0..candidates.len())
            .map(|k| scores[c].iter().map(|s| s[k]).sum::<f64>() / counts[c] as f64)
            .collect();
        // Chosen by how well neighbours' widths under other lights predict this light's
        // (leave-one-projector-out); the validation likelihood when that cannot be scored.
        chosen[c] = if width[c].len() >= 2 {
            candidates[most_pooled_within_one_se(&width[c], candidates)]
        } else {
            candidates[most_pooled_within_one_se(&scores[c], candidates)]
        };
        width_tables[c] = candidates
            .iter()
            .enumerate()
            .map(|(k, h)| {
                let n = width[c].len().max(1) as f64;
                (h.label(), -width[c].iter().map(|s| s[k]).sum::<f64>() / n)
            })
            .collect();
        tables[c] = candidates
            .iter()
            .zip(&means)
            .map(|(h, m)| (h.label(), *m))
            .collect();
    }
    Ok(Choice {
        chosen,
        tables,
        width_tables,
        counts,
    })
}

/// Log of the second moment (mm^2) of the profiles of pixel `i`, channel `c`, per training
/// projector (both axes pooled; `None` where that projector gives the pixel no light): a
/// one-number summary of the kernel width each light direction measured.
fn log_widths(inputs: &Inputs, i: usize, c: usize) -> Vec<Option<f64>> {
    inputs
        .geometries
        .iter()
        .zip(inputs.sweeps)
        .map(|(geo, sweep)| {
            let g = geo[i]?;
            let (mut m0, mut m2) = (0.0, 0.0);
            for a in 0..2 {
                if let Some(p) = sweep.profile(i, c, a, &g) {
                    for s in &p.samples {
                        let y = s.y.max(0.0);
                        m0 += y;
                        m2 += y * s.s * s.s;
                    }
                }
            }
            (m0 > 0.0 && m2 > 0.0).then(|| (m2 / m0).ln())
        })
        .collect()
}

/// Per tile and channel, the negated squared errors of predicting the validation pixel's log
/// width under each training projector `p` from the fitted pixels' widths under the OTHER
/// projectors, averaged over each candidate neighbourhood (leave-one-projector-out). A local
/// shape is worth keeping only if what neighbours measured under other lights predicts this
/// light: light-dependent errors (geometry, irradiance) are shared by neighbours under the same
/// light, which is why the validation likelihood alone favours local shapes too much.
fn width_loo_scores(inputs: &Inputs, candidates: &[Neighbourhood]) -> [Vec<Vec<f64>>; 3] {
    let tiles = inputs.tiles.count();
    let fitted: Vec<[Vec<Option<f64>>; 3]> = (0..tiles)
        .into_par_iter()
        .map(|t| match inputs.fitted_pixel(t) {
            Some(i) => std::array::from_fn(|c| log_widths(inputs, i, c)),
            None => Default::default(),
        })
        .collect();
    let projectors = inputs.geometries.len();
    // Global sums and counts per channel and projector.
    let mut sums = [
        vec![0.0; projectors],
        vec![0.0; projectors],
        vec![0.0; projectors],
    ];
    let mut counts = [
        vec![0usize; projectors],
        vec![0usize; projectors],
        vec![0usize; projectors],
    ];
    for f in &fitted {
        for c in 0..3 {
            for (p, x) in f[c].iter().enumerate() {
                if let Some(x) = x {
                    sums[c][p] += x;
                    counts[c][p] += 1;
                }
            }
        }
    }
    let per_tile: Vec<[Option<Vec<f64>>; 3]> = (0..tiles)
        .into_par_iter()
        .map(|t| {
            let mut out: [Option<Vec<f64>>; 3] = Default::default();
            let Some((v, exclude)) = inputs.validation_pixel(t) else {
                return out;
            };
            for (c, o) in out.iter_mut().enumerate() {
                let own = log_widths(inputs, v, c);
                let mut scores = vec![0.0; candidates.len()];
                let mut scored = false;
                for (p, x) in own.iter().enumerate() {
                    let Some(x) = x else { continue };
                    let mut preds = Vec::with_capacity(candidates.len());
                    for &hood in candidates {
                        let (mut s, mut n) = (0.0, 0usize);
                        match hood {
                            Neighbourhood::Global => {
                                for q in (0..projectors).filter(|&q| q != p) {
                                    s += sums[c][q];
                                    n += counts[c][q];
                                }
                            }
                            Neighbourhood::Radius(r) => {
                                for tile in inputs.window(t, r).filter(|&u| Some(u) != exclude) {
                                    for (q, y) in fitted[tile][c].iter().enumerate() {
                                        if let (true, Some(y)) = (q != p, y) {
                                            s += y;
                                            n += 1;
                                        }
                                    }
                                }
                            }
                        }
                        preds.push((n > 0).then(|| s / n as f64));
                    }
                    // Score a projector only when every candidate predicts it (a fair comparison).
                    if preds.iter().all(Option::is_some) {
                        scored = true;
                        for (acc, pred) in scores.iter_mut().zip(preds.into_iter().flatten()) {
                            *acc -= (x - pred).powi(2);
                        }
                    }
                }
                if scored {
                    *o = Some(scores);
                }
            }
            out
        })
        .collect();
    let mut out: [Vec<Vec<f64>>; 3] = Default::default();
    for tile in per_tile {
        for (c, s) in tile.into_iter().enumerate() {
            if let Some(s) = s {
                out[c].push(s);
            }
        }
    }
    out
}

/// Pooling rank of a candidate: the global shape pools most, then larger radii.
fn pooling(hood: Neighbourhood) -> usize {
    match hood {
        Neighbourhood::Global => usize::MAX,
        Neighbourhood::Radius(r) => r,
    }
}

/// The one-standard-error rule of cross-validation (Hastie, Tibshirani & Friedman, *Elements of
/// Statistical Learning*, 7.10): among the candidates whose mean validation score is within one
/// standard error of the best one's (the standard error of the per-tile score difference), the
/// most pooled. Why: the validation pixels are lit by the same projectors as the fitted tiles, so
/// light-dependent errors shared by neighbours (geometry, irradiance) make local shapes look
/// slightly better than they transfer to a new light; on the quick head with the estimated
/// calibration `r3` beat `global` by 0.002 nats per profile on validation and lost by 5 % of
/// held-out error.
fn most_pooled_within_one_se(scores: &[Vec<f64>], candidates: &[Neighbourhood]) -> usize {
    let n = scores.len() as f64;
    let mean = |k: usize| scores.iter().map(|s| s[k]).sum::<f64>() / n;
    let best = (0..candidates.len())
        .max_by(|&a, &b| mean(a).total_cmp(&mean(b)))
        .unwrap_or(0);
    let within = |k: usize| {
        if k == best {
            return true;
        }
        let d: Vec<f64> = scores.iter().map(|s| s[best] - s[k]).collect();
        let m = d.iter().sum::<f64>() / n;
        let var = d.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
        m <= (var / n).sqrt()
    };
    (0..candidates.len())
        .filter(|&k| within(k))
        .max_by_key(|&k| pooling(candidates[k]))
        .unwrap_or(best)
}

/// Variance components of the per-projector amplitude estimates of one channel.
#[derive(Debug, Clone, Copy, PartialEq)]
struct AmplitudeStats {
    mean: f64,
    /// Relative noise variance of one projector's estimate.
    noise: f64,
    /// Relative variance of the true amplitudes.
    signal: f64,
    /// Prior strength chosen by leave-one-projector-out prediction (see [`loo_kappa`]), and its
    /// mean squared error per left-out estimate.
    kappa: Option<f64>,
    cv_mse: Option<f64>,
}

/// Prior strengths tried by [`loo_kappa`] (0: each pixel keeps its own amplitude).
const KAPPAS: [f64; 16] = [
    0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 8.0, 13.0, 20.0, 50.0,
];

/// The amplitude prior strength `kappa` (a pixel seen by `n` projectors keeps `n / (n + kappa)`
/// of its relative deviation from the subject mean) that best predicts each training projector's
/// estimate from the pixel's other projectors, and that mean squared error. Unlike the moment
/// estimate it needs no assumption that the projectors' errors are independent: errors that
/// depend on the light direction (irradiance model, normals) do not carry over to a new
/// projector, and this choice sees that.
fn loo_kappa<E: AsRef<[f64]>>(per_pixel: &[E], mean: f64) -> Option<(f64, f64)> {
    if mean <= 0.0 {
        return None;
    }
    // One pass over the pixels for all kappas (each kappa's sum in pixel order).
    let mut sums = [0.0f64; KAPPAS.len()];
    let mut count = 0usize;
    for estimates in per_pixel.iter().map(AsRef::as_ref).filter(|e| e.len() >= 2) {
        let total: f64 = estimates.iter().map(|a| a / mean - 1.0).sum();
        let others = (estimates.len() - 1) as f64;
        for a in estimates {
            let d = a / mean - 1.0;
            for (sum, kappa) in sums.iter_mut().zip(KAPPAS) {
                // keep * mean of the others = sum of the others / (others + kappa).
                let predicted = (total - d) / (others + kappa);
                *sum += (d - predicted).powi(2);
            }
            count += 1;
        }
    }
    if count == 0 {
        return None;
    }
    let mut best: Option<(f64, f64)> = None;
    for (&kappa, sum) in KAPPAS.iter().zip(sums) {
        let mse = sum / count as f64;
        if best.is_none_or(|b| mse < b.1) {
            best = Some((kappa, mse));
        }
    }
    best
}

impl AmplitudeStats {
    /// Fraction of a pixel's deviation kept when `n` projectors measured it: `n / (n + kappa)`
    /// with the cross-validated prior strength, else the moment estimate `t2 / (t2 + s2 / n)`.
    fn keep(&self, n: usize) -> f64 {
        let n = n.max(1) as f64;
        if let Some(kappa) = self.kappa {
            return n / (n + kappa);
        }
        let denom = self.signal + self.noise / n;
        if denom > 0.0 {
            self.signal / denom
        } else {
            1.0
        }
    }
}

/// Method-of-moments variance components from per-pixel lists of per-projector estimates
/// (relative to their grand mean), and the subject mean `mean` of the pixel amplitudes.
fn amplitude_stats<E: AsRef<[f64]>>(per_pixel: &[E], mean: f64) -> AmplitudeStats {
    let mut none = AmplitudeStats {
        mean,
        noise: 0.0,
        signal: 0.0,
        kappa: None,
        cv_mse: None,
    };
    if mean <= 0.0 {
        return none;
    }
    let (mut within, mut dof) = (0.0, 0usize);
    let mut pixel_means = Vec::with_capacity(per_pixel.len());
    let mut noise_share = Vec::with_capacity(per_pixel.len());
    for estimates in per_pixel
        .iter()
        .map(AsRef::as_ref)
        .filter(|e| !e.is_empty())
    {
        let rel: Vec<f64> = estimates.iter().map(|a| a / mean - 1.0).collect();
        let m = rel.iter().sum::<f64>() / rel.len() as f64;
        within += rel.iter().map(|d| (d - m).powi(2)).sum::<f64>();
        dof += rel.len() - 1;
        pixel_means.push(m);
        noise_share.push(1.0 / rel.len() as f64);
    }
    if dof == 0 || pixel_means.len() < 2 {
        return none;
    }
    let noise = within / dof as f64;
    let grand = pixel_means.iter().sum::<f64>() / pixel_means.len() as f64;
    let between = pixel_means.iter().map(|m| (m - grand).powi(2)).sum::<f64>()
        / (pixel_means.len() - 1) as f64;
    let explained = noise * noise_share.iter().sum::<f64>() / noise_share.len() as f64;
    none.noise = noise;
    none.signal = (between - explained).max(0.0);
    none
}

/// The pipeline's call: with `enabled`, replaces `model` by its regularised version (default
/// options) and reports what was chosen; otherwise leaves it alone and returns `None`.
#[allow(clippy::too_many_arguments)]
pub fn regularise_in_place(
    enabled: bool,
    model: &mut LayerModel,
    surface: &Surface,
    geometries: &[Vec<Option<PixelGeometry>>],
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
    geometries: &[Vec<Option<PixelGeometry>>],
    sweeps: &[SlitSweep],
    block: usize,
    depth_spacing: f64,
    opts: &PriorOptions,
) -> Result<(LayerModel, PriorReport), SpatialPriorError> {
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
    let Choice {
        chosen,
        tables,
        width_tables,
        counts,
    } = choose_neighbourhoods(&inputs, &shapes, &global, &candidates)?;

    // Amplitudes: the fit's own per pixel, and per projector for the variance components.
    let n = surface.len();
    let own: Vec<[f64; 3]> = (0..n)
        .map(|i| {
            std::array::from_fn(|c| model.layers(i, c).iter().map(|l| f64::from(l.weight)).sum())
        })
        .collect();
    let per_projector: Vec<[Vec<f64>; 3]> = (0..n)
        .into_par_iter()
        .map(|i| {
            std::array::from_fn(|c| {
                if own[i][c] <= 0.0 {
                    return Vec::new();
                }
                projector_amplitudes(i, c, geometries, sweeps)
            })
        })
        .collect();
    // Channels in parallel; each reads its column of the per-projector lists in place.
    let stats: Vec<AmplitudeStats> = (0..3)
        .into_par_iter()
        .map(|c| {
            let with: Vec<f64> = own.iter().map(|a| a[c]).filter(|a| *a > 0.0).collect();
            let mean = if with.is_empty() {
                0.0
            } else {
                with.iter().sum::<f64>() / with.len() as f64
            };
            let lists: Vec<&[f64]> = per_projector.iter().map(|p| p[c].as_slice()).collect();
            let mut st = amplitude_stats(&lists, mean);
            if let Some((kappa, mse)) = loo_kappa(&lists, mean) {
                st.kappa = Some(kappa);
                st.cv_mse = Some(mse);
            }
            st
        })
        .collect();

    // Shapes of every tile under the chosen neighbourhoods, without the layers the renderer
    // skips by default.
    let final_shapes: Vec<[Option<Shape>; 3]> = (0..inputs.tiles.count())
        .into_par_iter()
        .map(|t| {
            std::array::from_fn(|c| {
                hood_shape(&inputs, &shapes, &global, t, c, chosen[c], None).map(without_faint)
            })
        })
        .collect();
    // The prior's shape and the fraction of the amplitude's deviation kept, where both apply.
    let prior_of = |i: usize, c: usize| -> Option<(&Shape, Option<f64>)> {
        if own[i][c] <= 0.0 {
            return None;
        }
        let shape = final_shapes[inputs.tiles.of_pixel(i)][c].as_ref()?;
        let st = &stats[c];
        let keep =
            (opts.shrink_amplitude && st.mean > 0.0).then(|| st.keep(per_projector[i][c].len()));
        Some((shape, keep))
    };
    let out = LayerModel::from_fn(surface.width, surface.height, |i, c| {
        let Some((shape, keep)) = prior_of(i, c) else {
            return model.layers(i, c).to_vec();
        };
        let (amplitude, mean) = (own[i][c], stats[c].mean);
        let target = keep.map_or(amplitude, |k| mean * (1.0 + k * (amplitude / mean - 1.0)));
        shape
            .iter()
            .map(|l| SplatLayer {
                weight: (f64::from(l.weight) * target) as f32,
                ..*l
            })
            .collect()
    });
    let mean_keep_fraction = |c: usize| {
        let keeps: Vec<f64> = (0..n).filter_map(|i| prior_of(i, c)?.1).collect();
        if keeps.is_empty() {
            1.0
        } else {
            keeps.iter().sum::<f64>() / keeps.len() as f64
        }
    };
    let channels = (0..3)
        .map(|c| ChannelPrior {
            shape: chosen[c].label(),
            cv_log_likelihood: tables[c].clone(),
            width_loo_mse: width_tables[c].clone(),
            amplitude_mean: stats[c].mean,
            noise_variance: stats[c].noise,
            signal_variance: stats[c].signal,
            amplitude_kappa: stats[c].kappa,
            amplitude_cv_mse: stats[c].cv_mse,
            mean_keep_fraction: mean_keep_fraction(c),
        })
        .collect();
    Ok((
        out,
        PriorReport {
            validation_pixels: counts,
            channels,
        },
    ))
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::fit::{FitOptions, fit_model};
    use crate::mixture::EmConfig;
    use crate::profiles::{AxisGeometry, SlitFrame};
    use mlsss_core::capture::{Axis, Pattern};

    const SIZE: usize = 30;
    const PERIOD: u32 = 10;
    /// The true layer shape everywhere: (weight fraction, sigma mm).
    const TRUE_SHAPE: [(f64, f64); 2] = [(0.6, 0.8), (0.4, 2.5)];

    fn layer(index: u16, weight: f32, sigma_mm: f32) -> SplatLayer {
        SplatLayer {
            index,
            weight,
            sigma_mm,
            depth_mm: 0.0,
        }
    }

    #[test]
    fn merging_keeps_bins_apart_and_moment_matches_within_a_bin() {
        // Two shapes: sigmas 1.0 and 1.05 share a bin (ratio 1.25), 3.0 does not.
        let a = vec![layer(0, 0.5, 1.0), layer(1, 0.5, 3.0)];
        let b = vec![layer(0, 1.0, 1.05)];
        let m = merged_mixture([a, b].iter(), 1.25).unwrap();
        assert_eq!(m.len(), 2, "{m:?}");
        let narrow = m.iter().find(|l| l.sigma_mm < 2.0).unwrap();
        let wide = m.iter().find(|l| l.sigma_mm > 2.0).unwrap();
        // Equal-weight mixture: narrow (0.5 + 1.0) / 2, wide 0.5 / 2.
        assert!((narrow.weight - 0.75).abs() < 1e-6);
        assert!((wide.weight - 0.25).abs() < 1e-6);
        let var = (0.5 * 1.0 + 1.0 * 1.05f64.powi(2)) / 1.5;
        assert!((f64::from(narrow.sigma_mm) - var.sqrt()).abs() < 1e-5);
        assert_eq!(f64::from(wide.sigma_mm), 3.0);
        // At depth 0 every index is one family: codes share depth index 0 and differ by bin.
        assert_eq!(narrow.index / SIGMA_BINS, 0);
        assert_eq!(wide.index / SIGMA_BINS, 0);
        assert_ne!(narrow.index, wide.index);
        // Same sigma, different depths: one layer at the weight-averaged depth.
        let deep = |index: u16, depth: f32| SplatLayer {
            depth_mm: depth,
            ..layer(index, 0.5, 1.0)
        };
        let c = vec![deep(1, 0.1), deep(2, 0.2)];
        let d = vec![deep(1, 0.1)];
        let m = merged_mixture([c, d].iter(), 1.25).unwrap();
        assert_eq!(m.len(), 1, "{m:?}");
        assert!((m[0].weight - 0.75).abs() < 1e-6);
        // Weights 0.5 at 0.1 (twice) and 0.5 at 0.2: mean depth 0.4 / 3.
        assert!((f64::from(m[0].depth_mm) - 0.4 / 3.0).abs() < 1e-6, "{m:?}");
        assert!(merged_mixture(std::iter::empty(), 1.25).is_none());
    }

    /// Regression (full-size model 1.8x too large): faint layers of a shape are not stored, and
    /// a default render of the model does not change for it, to the bit.
    #[test]
    fn faint_layers_are_dropped_without_changing_a_default_render() {
        let shape = vec![
            layer(0, 0.55, 0.3),
            layer(1, 0.0009, 0.5),
            layer(2, 0.4, 1.2),
            layer(3, 0.0004, 2.5),
            layer(4, 0.0487, 4.0),
        ];
        let kept = without_faint(shape.clone());
        assert_eq!(kept, vec![shape[0], shape[2], shape[4]]);

        let (w, h, pitch) = (48, 40, 0.1);
        let surface = Surface::flat(w, h, pitch, Vector3::new(0.0, 0.0, 1e4));
        let mut rng = Pcg64::seed_from_u64(5);
        let irradiance: Vec<f32> = (0..w * h).map(|_| rng.gen_range(0.0..1.0)).collect();
        let amplitude: Vec<f32> = (0..w * h).map(|_| rng.gen_range(0.2..0.9)).collect();
        let scaled = |s: &Shape, i: usize| -> Vec<SplatLayer> {
            s.iter()
                .map(|l| SplatLayer {
                    weight: l.weight * amplitude[i],
                    ..*l
                })
                .collect()
        };
        let shift = vec![Some(Vector3::new(0.3, -0.2, 0.0)); w * h];
        let opts = RenderOptions::default();
        let render = |s: &Shape| {
            let model = LayerModel::from_fn(w, h, |i, _| scaled(s, i));
            crate::render::render_global(&surface, &irradiance, &shift, &model, &opts).unwrap()
        };
        assert_eq!(render(&shape), render(&kept));
    }

    #[test]
    fn variance_components_are_recovered_from_per_projector_estimates() {
        // True relative deviations with variance 0.04, three projectors with noise variance 0.01.
        let mut rng = Pcg64::seed_from_u64(7);
        let mut normal = |sd: f64| {
            let (u, v): (f64, f64) = (rng.r#gen::<f64>().max(1e-12), rng.r#gen());
            sd * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let mean = 2.0;
        let lists: Vec<Vec<f64>> = (0..20_000)
            .map(|_| {
                let truth = 1.0 + normal(0.2);
                (0..3).map(|_| mean * (truth + normal(0.1))).collect()
            })
            .collect();
        let st = amplitude_stats(&lists, mean);
        assert!((st.signal - 0.04).abs() < 0.003, "{st:?}");
        assert!((st.noise - 0.01).abs() < 0.0005, "{st:?}");
        // Posterior keep fraction for 3 projectors: 0.04 / (0.04 + 0.01 / 3).
        assert!((st.keep(3) - 0.04 / (0.04 + 0.01 / 3.0)).abs() < 0.01);
        // One estimate per pixel: no noise estimate, nothing shrunk.
        let single: Vec<Vec<f64>> = lists.iter().map(|l| vec![l[0]]).collect();
        assert_eq!(amplitude_stats(&single, mean).keep(1), 1.0);
    }

    #[test]
    fn loo_kappa_recovers_the_posterior_keep_fraction() {
        let mut rng = Pcg64::seed_from_u64(11);
        let mut normal = |sd: f64| {
            let (u, v): (f64, f64) = (rng.r#gen::<f64>().max(1e-12), rng.r#gen());
            sd * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let mean = 0.3;
        // True relative deviations with variance 0.04, three projectors with independent noise
        // of variance 0.01: the posterior keeps 0.04 / (0.04 + 0.01 / 3) of a pixel's deviation.
        let plain: Vec<Vec<f64>> = (0..20_000)
            .map(|_| {
                let t = normal(0.2);
                (0..3).map(|_| mean * (1.0 + t + normal(0.1))).collect()
            })
            .collect();
        let (kappa, _) = loo_kappa(&plain, mean).unwrap();
        let want = 0.04 / (0.04 + 0.01 / 3.0);
        assert!((3.0 / (3.0 + kappa) - want).abs() < 0.03, "kappa {kappa}");
        // No true variation, only noise: almost everything is shrunk away.
        let noise: Vec<Vec<f64>> = (0..20_000)
            .map(|_| (0..3).map(|_| mean * (1.0 + normal(0.1))).collect())
            .collect();
        let (kappa, _) = loo_kappa(&noise, mean).unwrap();
        assert!(3.0 / (3.0 + kappa) < 0.2, "kappa {kappa}");
    }

    /// Boxed Gaussian mass of a 1 mm slit at distance `s` (mm), with the comb's neighbours, for
    /// the true shape with its sigmas scaled by `scale`.
    fn true_profile(s: f64, scale: f64) -> f64 {
        TRUE_SHAPE
            .iter()
            .map(|&(w, sigma)| {
                let k = scale * sigma * std::f64::consts::SQRT_2;
                (-1..=1)
                    .map(|m| {
                        let d = s - f64::from(m) * f64::from(PERIOD);
                        0.5 * (libm::erf((d + 0.5) / k) - libm::erf((d - 0.5) / k))
                    })
                    .sum::<f64>()
                    * w
            })
            .sum()
    }

    /// A synthetic capture: a flat `SIZE x SIZE` patch, 1 mm per projector pixel, three
    /// projectors with their own irradiance, each pixel's irradiance model off by a random
    /// factor per projector (the non-transferable error), camera noise on the slit frames.
    struct Scene {
        surface: Surface,
        geometries: Vec<Vec<Option<PixelGeometry>>>,
        frames: Vec<Vec<(Pattern, Vec<[f32; 3]>)>>,
    }

    fn scene(amplitude: impl Fn(usize) -> f64, scale: impl Fn(usize) -> f64, seed: u64) -> Scene {
        let n = SIZE * SIZE;
        let mut rng = Pcg64::seed_from_u64(seed);
        let surface = Surface {
            width: SIZE,
            height: SIZE,
            points: (0..n)
                .map(|i| Vector3::new((i % SIZE) as f64, (i / SIZE) as f64, 0.0))
                .collect(),
            normals: vec![Vector3::z(); n],
            mask: vec![true; n],
            camera_centre: Vector3::new(15.0, 15.0, 1000.0),
        };
        let axis = AxisGeometry {
            px_per_mm: 1.0,
            shift_per_depth: 0.0,
        };
        let mut geometries = Vec::new();
        let mut frames = Vec::new();
        for (p, irradiance) in [1.0, 0.8, 1.2].into_iter().enumerate() {
            let offset = 0.37 * p as f64;
            let geo: Vec<Option<PixelGeometry>> = (0..n)
                .map(|i| {
                    Some(PixelGeometry {
                        coords: ((i % SIZE) as f64 + offset, (i / SIZE) as f64 - offset),
                        irradiance,
                        axes: [axis; 2],
                        shift: Vector3::zeros(),
                    })
                })
                .collect();
            // The light really delivered differs from the model's by a few per cent per pixel.
            let delivered: Vec<f64> = (0..n)
                .map(|_| irradiance * (1.0 + 0.08 * (rng.r#gen::<f64>() - 0.5) * 3.46))
                .collect();
            let mut sweep = Vec::new();
            for (a, ax) in [Axis::X, Axis::Y].into_iter().enumerate() {
                for o in 0..PERIOD {
                    let pattern = Pattern::Slit {
                        axis: ax,
                        width: 1,
                        period: PERIOD,
                        offset: o,
                    };
                    let img: Vec<[f32; 3]> = (0..n)
                        .map(|i| {
                            let g = geo[i].unwrap();
                            let coord = if a == 0 { g.coords.0 } else { g.coords.1 };
                            let s = super::super::profiles::slit_distance_px(coord, 1, PERIOD, o);
                            let clean = delivered[i] * amplitude(i) * true_profile(s, scale(i));
                            std::array::from_fn(|_| {
                                let noise = 0.004 * (rng.r#gen::<f64>() - 0.5) * 3.46;
                                (clean + noise) as f32
                            })
                        })
                        .collect();
                    sweep.push((pattern, img));
                }
            }
            geometries.push(geo);
            frames.push(sweep);
        }
        Scene {
            surface,
            geometries,
            frames,
        }
    }

    /// The scene's slit frames as the fit stage sees them, one list per projector.
    fn slit_frames(s: &Scene) -> Vec<Vec<SlitFrame<'_>>> {
        s.frames
            .iter()
            .map(|f| {
                f.iter()
                    .map(|(pattern, img)| SlitFrame {
                        pattern: *pattern,
                        global: img,
                    })
                    .collect()
            })
            .collect()
    }

    /// One slit sweep per projector over `frames`.
    fn sweeps<'a>(frames: &'a [Vec<SlitFrame<'a>>]) -> Vec<SlitSweep<'a>> {
        frames
            .iter()
            .map(|f| SlitSweep::new(f, SIZE * SIZE).unwrap())
            .collect()
    }

    /// Fits the scene like the fit stage (3 x 3 tiles, up to 4 components) and applies the prior.
    fn fit_and_regularise(s: &Scene) -> (LayerModel, LayerModel, PriorReport) {
        let slit_frames = slit_frames(s);
        let sweeps = sweeps(&slit_frames);
        let opts = FitOptions {
            em: EmConfig {
                components: 3,
                max_iterations: 40,
                ..EmConfig::default()
            },
            depth_spacing: Some(0.0),
            block: 3,
            ..FitOptions::default()
        };
        let fit = fit_model(&s.surface, &s.geometries, &sweeps, &opts).unwrap();
        let (out, report) = regularise(
            &fit.model,
            &s.surface,
            &s.geometries,
            &sweeps,
            3,
            0.0,
            &PriorOptions::default(),
        )
        .unwrap();
        (fit.model, out, report)
    }

    fn total(model: &LayerModel, i: usize, c: usize) -> f64 {
        model.layers(i, c).iter().map(|l| f64::from(l.weight)).sum()
    }

    /// Second moment `sum w sigma^2 / sum w` of a pixel's kernel (mm^2).
    fn second_moment(model: &LayerModel, i: usize, c: usize) -> f64 {
        let l = model.layers(i, c);
        l.iter()
            .map(|l| f64::from(l.weight) * f64::from(l.sigma_mm).powi(2))
            .sum::<f64>()
            / total(model, i, c)
    }

    fn rel_rms(values: impl Iterator<Item = (f64, f64)>) -> f64 {
        let (mut num, mut den) = (0.0, 0.0);
        for (got, want) in values {
            num += (got - want).powi(2);
            den += want * want;
        }
        (num / den).sqrt()
    }

    #[test]
    fn free_em_fit_stage_recovers_amplitude_and_width_of_uniform_skin() {
        // `--em free` (the paper's variant) through the fit stage on the synthetic patch: every
        // pixel gets layers, the absolute weights add up to the true amplitude (the flux
        // normalisation), and the kernel's second moment is the truth's within the loss the
        // paper's rank averaging of sigmas causes.
        let truth = 0.3;
        let s = scene(|_| truth, |_| 1.0, 13);
        let slit_frames = slit_frames(&s);
        let sweeps = sweeps(&slit_frames);
        let opts = FitOptions {
            em: EmConfig {
                components: 3,
                max_iterations: 60,
                ..EmConfig::default()
            },
            variant: crate::fit::EmVariant::Free,
            block: 3,
            ..FitOptions::default()
        };
        let fit = fit_model(&s.surface, &s.geometries, &sweeps, &opts).unwrap();
        let n = SIZE * SIZE;
        assert_eq!(fit.stats.depth_spacing_mm, 0.0);
        assert!((0..n).all(|i| !fit.model.layers(i, 0).is_empty()));
        let amplitude = rel_rms((0..n).map(|i| (total(&fit.model, i, 0), truth)));
        assert!(amplitude < 0.1, "amplitude rel RMS error {amplitude}");
        let m2: f64 = TRUE_SHAPE.iter().map(|(w, s)| w * s * s).sum();
        let width = rel_rms((0..n).map(|i| (second_moment(&fit.model, i, 0), m2)));
        assert!(width < 0.35, "kernel second moment rel RMS error {width}");
        // No depth without geometry that moves the layers (shift_per_depth 0 here).
        assert!((0..n).all(|i| {
            fit.model
                .layers(i, 0)
                .iter()
                .all(|l| l.depth_mm == 0.0 && l.weight.is_finite() && l.sigma_mm > 0.0)
        }));
    }

    #[test]
    fn uniform_skin_noise_is_shrunk_away() {
        let truth = 0.3;
        let s = scene(|_| truth, |_| 1.0, 11);
        let (raw, reg, report) = fit_and_regularise(&s);
        let n = SIZE * SIZE;
        let err = |m: &LayerModel| rel_rms((0..n).map(|i| (total(m, i, 0), truth)));
        let (before, after) = (err(&raw), err(&reg));
        // Nothing real varies: most of each pixel's deviation is noise and goes.
        assert!(report.channels[0].mean_keep_fraction < 0.5, "{report:?}");
        assert!(after < 0.6 * before, "amplitude error {before} -> {after}");
        // Shapes: one shape fits all, so the cross-validation pools neighbours, and the kernel's
        // second moment gets closer to the truth's.
        assert_ne!(report.channels[0].shape, "r0", "{report:?}");
        let m2: f64 = TRUE_SHAPE.iter().map(|(w, s)| w * s * s).sum();
        let shape_err = |m: &LayerModel| rel_rms((0..n).map(|i| (second_moment(m, i, 0), m2)));
        let (sb, sa) = (shape_err(&raw), shape_err(&reg));
        assert!(sa < sb, "second-moment error {sb} -> {sa}");
    }

    #[test]
    fn a_real_material_edge_is_kept() {
        // Two materials: the left half re-emits twice what the right half does.
        let amp = |i: usize| if i % SIZE < SIZE / 2 { 0.4 } else { 0.2 };
        let s = scene(amp, |_| 1.0, 12);
        let (raw, reg, report) = fit_and_regularise(&s);
        // The true variation dwarfs the noise: deviations are kept.
        assert!(report.channels[0].mean_keep_fraction > 0.9, "{report:?}");
        let half_mean = |m: &LayerModel, left: bool| {
            let px: Vec<usize> = (0..SIZE * SIZE)
                .filter(|i| (i % SIZE < SIZE / 2 - 2) == left && (i % SIZE > SIZE / 2 + 1) != left)
                .collect();
            px.iter().map(|&i| total(m, i, 1)).sum::<f64>() / px.len() as f64
        };
        for (left, want) in [(true, 0.4), (false, 0.2)] {
            let (b, a) = (half_mean(&raw, left), half_mean(&reg, left));
            assert!(
                (a - want).abs() < 0.05 * want,
                "left={left}: {b} -> {a}, truth {want}"
            );
        }
        let n = SIZE * SIZE;
        let err = |m: &LayerModel| rel_rms((0..n).map(|i| (total(m, i, 1), amp(i))));
        assert!(
            err(&reg) <= err(&raw) * 1.02,
            "{} -> {}",
            err(&raw),
            err(&reg)
        );
    }

    #[test]
    fn shapes_are_not_pooled_across_a_change_of_material() {
        // Same amplitude, but the right half scatters twice as wide: one global shape would be
        // wrong on both sides, so the cross-validation keeps shapes local.
        let scale = |i: usize| if i % SIZE < SIZE / 2 { 1.0 } else { 2.0 };
        let s = scene(|_| 0.3, scale, 14);
        let (raw, reg, report) = fit_and_regularise(&s);
        assert!(
            ["r0", "r1"].contains(&report.channels[0].shape.as_str()),
            "{report:?}"
        );
        let m2 = |i: usize| -> f64 {
            TRUE_SHAPE
                .iter()
                .map(|(w, s)| w * (s * scale(i)).powi(2))
                .sum()
        };
        let n = SIZE * SIZE;
        let shape_err = |m: &LayerModel| rel_rms((0..n).map(|i| (second_moment(m, i, 0), m2(i))));
        let (sb, sa) = (shape_err(&raw), shape_err(&reg));
        assert!(sa <= sb * 1.001, "second-moment error {sb} -> {sa}");
    }

    #[test]
    fn switched_off_the_model_is_untouched() {
        let s = scene(|_| 0.3, |_| 1.0, 13);
        let raw = LayerModel::from_fn(SIZE, SIZE, |i, c| {
            vec![layer(0, 0.3 + (i % 7) as f32 * 0.01, 1.0 + c as f32)]
        });
        let mut same = raw.clone();
        let geometries = s.geometries.clone();
        let frames: Vec<SlitFrame> = s.frames[0]
            .iter()
            .map(|(pattern, img)| SlitFrame {
                pattern: *pattern,
                global: img,
            })
            .collect();
        let sweeps = vec![SlitSweep::new(&frames, SIZE * SIZE).unwrap()];
        let report = regularise_in_place(
            false,
            &mut same,
            &s.surface,
            &geometries[..1],
            &sweeps,
            3,
            0.0,
        )
        .unwrap();
        assert!(report.is_none());
        assert_eq!(same, raw);
        // Mismatched inputs are refused, not guessed.
        assert!(matches!(
            regularise_in_place(true, &mut same, &s.surface, &geometries, &sweeps, 3, 0.0),
            Err(SpatialPriorError::ProjectorCount { .. })
        ));
    }
}
