//! The layer spacing `D` of the layered model (DESIGN section 5): one value for the whole subject,
//! estimated by maximum likelihood over a sample of pixels.
//!
//! Physics
//! - Light refracted into the skin at angle `theta_t` travels away from the light before it
//!   scatters, so the light that re-emerges is shifted forward, away from the light; less of it
//!   emerges on the side the light came from (back-scatter). In a diffusive medium the shift of the
//!   exit centroid is about one transport mean free path along the refracted ray,
//!   `sin(theta_t) / (mu_s' + mu_a)` (Wang & Jacques 1995, oblique-incidence reflectometry). The
//!   virtual booth's Monte Carlo shows it: for `host/monte-carlo/data/skin-layers.toml` (mu_s' 0.88,
//!   mu_a 0.17 per mm) the exit centroid moves 0.34, 0.47, 0.58 mm at 30, 45, 60 degrees of
//!   incidence, i.e. 0.93 `sin(theta_t)` mm (`mlsss mc layers --file .. --angle A --json`,
//!   `exit_centroid_mm`).
//! - The layered model reproduces that shift with depth: layer `l` sits at `z_l = l D` and the
//!   light reaching it has moved `z_l t_i` (`|t_i| = tan(theta_t)`), so a profile's centroid moves
//!   by `zbar c_p` with `zbar = sum_l w_l z_l` the weight-averaged layer depth.
//! - The view term `t_o` (paper eq. 5) moves where the camera sees a layer. Diffuse light leaving
//!   the skin does not remember the depth it was scattered at, and the virtual booth's truth is
//!   exitance at the exit point: with [`ViewRay::ExitPoint`](super::surface::ViewRay) `t_o = 0`
//!   and `c_p = t_i . s_hat_p` carries the light's direction alone. With `t_o` in `c_p`, two
//!   profiles of the same light direction seen from two view directions ask for different shifts
//!   that the data do not show, which pulls `D` toward 0.
//!
//! Estimator
//! - Each sampled pixel-channel is one joint layered fit of its profiles (3 projectors x 2 axes)
//!   at a shared `D`; `D` is then updated by the conditional M-step of the pooled likelihood (the
//!   normal equations `num / den` of every pixel summed, [`em_layered::spacing_moments`]), and the
//!   pixels are refitted from their last parameters, until `D` moves less than
//!   [`TOLERANCE_MM`]. Every step raises the pooled likelihood (a generalised EM), and no
//!   pixel's estimate is clamped on its own: a pixel whose noise leans toward the light pulls the
//!   sum down by its weight instead of voting "0" in a median (the previous estimator took the
//!   median of per-pixel estimates clamped at 0 and returned exactly 0 as soon as half of them
//!   leaned negative).
//! - Only the pooled value is clamped to `[0, max]`.
//! - Limit (measured on the quick demo, 195 sampled pixel-channels): the training profiles pin
//!   `D` down only weakly. The pooled log-likelihood, each set refitted from scratch at each `D`,
//!   rises by 0.006 per set from `D` = 0 to 1 mm (at 1 mm the deep layers keep little weight;
//!   mean depth 0.47 mm), and the ECM started at the default 0.1 mm stops after one round at
//!   0.0999 mm (mean depth 0.14 mm): with a likelihood this flat the start acts as a prior. The
//!   held-out projector prefers the latter: back-scatter asymmetry 0.915 against the truth's
//!   0.897 (0.950 with `D` = 0.99 mm), global relative RMSE 0.1135 against 0.1129.
//!
//! Conventions as in [`super::profiles`]: `s` in mm on the surface, `c_p` the shift per mm of
//! depth along the profile axis, positive away from the light.

use rayon::prelude::*;

use super::em_layered::{self, DepthSpacing, LayeredParams};
use super::fit_options::FitOptions;
use super::mixture::{EmConfig, EmError, Profile};
use super::profiles::{GeometryMap, SlitSweep, pixel_profiles};

/// Stop when one round moves `D` by less than this (mm).
pub const TOLERANCE_MM: f64 = 1e-3;

/// At most this many rounds of refit + spacing update.
pub const MAX_ROUNDS: usize = 30;

/// Errors of the spacing estimate.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum LayerDepthError {
    /// The EM fit of one sampled pixel-channel failed on something other than missing light.
    #[error("layer spacing, sampled set {set}: {source}")]
    Em { set: usize, source: EmError },
    /// No sampled pixel has light and a light direction that moves its layers.
    #[error(
        "no sampled pixel constrains the layer spacing (no light in the profiles, or every light \
         along the normal)"
    )]
    Unconstrained,
}

/// How the spacing was found.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SpacingEstimate {
    /// The layer spacing `D` (mm).
    pub spacing_mm: f64,
    /// Pixel-channel profile sets that entered the estimate.
    pub sets: usize,
    /// Rounds of refit + spacing update run.
    pub rounds: usize,
    /// Weight-averaged layer depth `sum_l w_l z_l` (mm), mean over the sets, at the estimate.
    pub mean_depth_mm: f64,
    /// Median of the sets' own spacing (`num / den` of one set alone, unclamped) at the
    /// estimate: how the pixels spread around the pooled value.
    pub median_set_spacing_mm: f64,
    /// Fraction of sets whose own spacing is negative (profiles leaning toward the light).
    pub negative_fraction: f64,
}

impl SpacingEstimate {
    /// A spacing given, not estimated.
    pub fn fixed(spacing_mm: f64) -> Self {
        Self {
            spacing_mm,
            ..Self::default()
        }
    }
}

/// Pixels whose layers barely move with depth (`sum_p |c_p|` below this) say nothing about `D`.
const MIN_LEVERAGE: f64 = 1e-3;

/// One set's fit at the current spacing and its normal equations `(num, den)`; `None` without
/// light.
type SetFit = Option<(LayeredParams, (f64, f64))>;

/// One round: every set fitted at `spacing` (from its last parameters), and its normal equations.
fn refit_round(
    sets: &[Vec<Profile>],
    warm: &[Option<LayeredParams>],
    spacing: f64,
    em: &EmConfig,
) -> Result<Vec<SetFit>, LayerDepthError> {
    sets.par_iter()
        .zip(warm)
        .enumerate()
        .map(|(set, (profiles, warm))| {
            let wrap = |source| LayerDepthError::Em { set, source };
            let fit = match em_layered::fit_layered(
                profiles,
                DepthSpacing::Fixed(spacing),
                em,
                warm.as_ref(),
            ) {
                Ok(fit) => fit,
                Err(EmError::NoSignal) => return Ok(None),
                Err(e) => return Err(wrap(e)),
            };
            let params = LayeredParams {
                layers: fit.layers,
                depth_spacing: spacing,
            };
            let moments =
                em_layered::spacing_moments(profiles, &params, em.wrap_images).map_err(wrap)?;
            Ok(Some((params, moments)))
        })
        .collect()
}

/// Maximum-likelihood spacing shared by every set of `sets` (each set: one pixel-channel's
/// profiles), starting at `start` mm, clamped to `[0, max]` (see the module doc).
pub fn pooled_spacing(
    sets: &[Vec<Profile>],
    start: f64,
    max: f64,
    em: &EmConfig,
) -> Result<SpacingEstimate, LayerDepthError> {
    let sets: Vec<Vec<Profile>> = sets
        .iter()
        .filter(|set| set.iter().map(|p| p.shift_per_depth.abs()).sum::<f64>() >= MIN_LEVERAGE)
        .cloned()
        .collect();
    let mut spacing = start.clamp(0.0, max);
    let mut warm: Vec<Option<LayeredParams>> = vec![None; sets.len()];
    let mut rounds = 0;
    let mut last = Vec::new();
    while rounds < MAX_ROUNDS {
        rounds += 1;
        last = refit_round(&sets, &warm, spacing, em)?;
        let (num, den) = last
            .iter()
            .flatten()
            .fold((0.0, 0.0), |(n, d), (_, (a, b))| (n + a, d + b));
        if den <= 1e-300 {
            return Err(LayerDepthError::Unconstrained);
        }
        let next = (num / den).clamp(0.0, max);
        warm = last
            .iter()
            .map(|r| r.as_ref().map(|r| r.0.clone()))
            .collect();
        let step = (next - spacing).abs();
        spacing = next;
        if step < TOLERANCE_MM {
            break;
        }
    }
    summarise(spacing, rounds, &last)
}

/// The subject's spacing from up to `opts.spacing_pixels` pixels spread evenly over `lit`
/// (every channel), or `opts.depth_spacing` when it is given.
pub fn estimate_spacing(
    lit: &[usize],
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    opts: &FitOptions,
) -> Result<SpacingEstimate, LayerDepthError> {
    if let Some(d) = opts.depth_spacing {
        return Ok(SpacingEstimate::fixed(d));
    }
    let step = (lit.len() / opts.spacing_pixels.max(1)).max(1);
    let sets: Vec<Vec<Profile>> = lit
        .iter()
        .step_by(step)
        .flat_map(|&i| (0..3).map(move |c| (i, c)))
        .map(|(i, c)| pixel_profiles(i, c, geometries, sweeps).0)
        .collect();
    // The fits only rank the spacing: fewer iterations, no model selection. The plain EM: its
    // fits stop at 80 iterations, short of convergence for some sets, so SQUAREM's would move
    // the estimate (0.1516 -> 0.1488 mm on the full-size head) and with it every layer's depth.
    let em = EmConfig {
        max_iterations: opts.em.max_iterations.min(80),
        bic: false,
        squarem: false,
        ..opts.em.clone()
    };
    pooled_spacing(&sets, opts.spacing_start, opts.spacing_max, &em)
}

/// The estimate and the spread of the sets around it.
fn summarise(
    spacing: f64,
    rounds: usize,
    fits: &[SetFit],
) -> Result<SpacingEstimate, LayerDepthError> {
    let fitted: Vec<&(LayeredParams, (f64, f64))> = fits.iter().flatten().collect();
    if fitted.is_empty() {
        return Err(LayerDepthError::Unconstrained);
    }
    let mut own: Vec<f64> = fitted
        .iter()
        .filter(|f| f.1.1 > 1e-300)
        .map(|f| f.1.0 / f.1.1)
        .collect();
    own.sort_by(f64::total_cmp);
    let mean_depth = fitted
        .iter()
        .map(|f| {
            f.0.layers
                .iter()
                .map(|l| l.weight * l.depth_index as f64 * spacing)
                .sum::<f64>()
        })
        .sum::<f64>()
        / fitted.len() as f64;
    Ok(SpacingEstimate {
        spacing_mm: spacing,
        sets: fitted.len(),
        rounds,
        mean_depth_mm: mean_depth,
        median_set_spacing_mm: own.get(own.len() / 2).copied().unwrap_or(f64::NAN),
        negative_fraction: own.iter().filter(|&&d| d < 0.0).count() as f64
            / own.len().max(1) as f64,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::em_layered::Layer;
    use crate::mixture::Sample;

    /// Slit width and period (mm) and the sample spacing of the synthetic profiles.
    const W: f64 = 0.6;
    const T: f64 = 18.0;

    /// The exact profile of a layered model through a slit comb: each layer a Gaussian at
    /// `z_l c` convolved with the box, with its images one period away (as the sweep sees it).
    fn profile(params: &LayeredParams, c: f64) -> Profile {
        let cdf = |x: f64| 0.5 * mlsss_core::special::erfc(-x / std::f64::consts::SQRT_2);
        let samples = (0..30)
            .map(|j| {
                let s = -T / 2.0 + (j as f64 + 0.5) * T / 30.0;
                let y = params
                    .layers
                    .iter()
                    .map(|l| {
                        let mu = l.depth_index as f64 * params.depth_spacing * c;
                        (-1..=1)
                            .map(|m| {
                                let x = s - mu - m as f64 * T;
                                cdf((x + W / 2.0) / l.sigma) - cdf((x - W / 2.0) / l.sigma)
                            })
                            .sum::<f64>()
                            * l.weight
                            / W
                    })
                    .sum();
                Sample { s, y }
            })
            .collect();
        Profile {
            noise: None,
            samples,
            slit_width: W,
            period: Some(T),
            shift_per_depth: c,
        }
    }

    /// Pixels of one skin with true spacing `d`: layer weights and widths vary from pixel to
    /// pixel, and each pixel sees 3 lights along 2 axes with its own geometry.
    fn pixels(d: f64, n: usize) -> Vec<Vec<Profile>> {
        (0..n)
            .map(|i| {
                let f = i as f64 / n as f64;
                let params = LayeredParams {
                    layers: vec![
                        Layer {
                            depth_index: 0,
                            weight: 0.3 + 0.2 * f,
                            sigma: 0.5,
                        },
                        Layer {
                            depth_index: 1,
                            weight: 0.4 - 0.1 * f,
                            sigma: 1.1,
                        },
                        Layer {
                            depth_index: 3,
                            weight: 0.3 - 0.1 * f,
                            sigma: 2.2 + 0.5 * f,
                        },
                    ],
                    depth_spacing: d,
                };
                // Light directions of 3 projectors around the pixel, both slit axes.
                let phase = 2.0 * std::f64::consts::PI * f;
                (0..3)
                    .flat_map(|k| {
                        let a = phase + k as f64 * 2.1;
                        let t = 0.3 + 0.3 * ((i + k) % 3) as f64 / 2.0;
                        [t * a.cos(), t * a.sin()]
                    })
                    .map(|c| profile(&params, c))
                    .collect()
            })
            .collect()
    }

    fn em() -> EmConfig {
        EmConfig {
            components: 4,
            max_iterations: 120,
            bic: false,
            ..EmConfig::default()
        }
    }

    #[test]
    fn pooled_spacing_recovers_a_known_spacing() {
        for d in [0.2, 0.45] {
            let est = pooled_spacing(&pixels(d, 12), 0.1, 1.0, &em()).unwrap();
            // The fitted layers need not sit on the true indices: D trades against the index of
            // the deep layer, the mean depth (what the profiles show) does not.
            let want_mean_depth = (0..12)
                .map(|i| {
                    let f = f64::from(i) / 12.0;
                    ((0.4 - 0.1 * f) + 3.0 * (0.3 - 0.1 * f)) * d
                })
                .sum::<f64>()
                / 12.0;
            eprintln!("D {d}: {est:?}, true mean depth {want_mean_depth:.4}");
            assert!(
                (est.mean_depth_mm / want_mean_depth - 1.0).abs() < 0.1,
                "D {d}: mean depth {} vs {want_mean_depth}",
                est.mean_depth_mm
            );
            assert!(
                est.spacing_mm > 0.0 && est.negative_fraction < 0.2,
                "{est:?}"
            );
        }
    }

    #[test]
    fn symmetric_profiles_give_zero_spacing() {
        let est = pooled_spacing(&pixels(0.0, 12), 0.3, 1.0, &em()).unwrap();
        assert!(est.spacing_mm < 0.02, "{est:?}");
    }

    #[test]
    fn pixels_without_leverage_are_unconstrained() {
        let flat: Vec<Vec<Profile>> = pixels(0.3, 4)
            .into_iter()
            .map(|set| {
                set.into_iter()
                    .map(|p| Profile {
                        shift_per_depth: 0.0,
                        ..p
                    })
                    .collect()
            })
            .collect();
        assert_eq!(
            pooled_spacing(&flat, 0.1, 1.0, &em()),
            Err(LayerDepthError::Unconstrained)
        );
    }

    /// The virtual booth's Monte Carlo (MCML physics, independent of the layer model) for a
    /// pencil beam at `deg` of incidence from the -x side: the exit centroid along x (mm,
    /// unbinned) and the exit response integrated across y and x (the slit profiles along x and
    /// along y, one cell wide slits).
    fn monte_carlo(deg: f64) -> (f64, Vec<f64>, Vec<f64>, f64) {
        use mlsss_mc::{self, GridSpec, Layer as McLayer, McConfig, Medium};
        let medium = Medium::slab(
            McLayer {
                thickness_mm: f64::INFINITY,
                mu_a: 0.5,
                mu_s: 5.0,
                g: 0.8,
                n: 1.4,
            },
            1.0,
            1.0,
        );
        let grid = GridSpec {
            cell_mm: 0.25,
            cells: 41,
        };
        let cfg = McConfig {
            incidence_deg: deg,
            grid: Some(grid),
            ..McConfig::new(40_000, 7)
        };
        let run = mlsss_mc::run(&medium, &cfg).unwrap();
        let r = run.response.unwrap();
        let along_x = (0..r.cells)
            .map(|ix| (0..r.cells).map(|iy| r.value(ix, iy)).sum::<f64>() * r.cell_mm)
            .collect();
        let along_y = (0..r.cells)
            .map(|iy| (0..r.cells).map(|ix| r.value(ix, iy)).sum::<f64>() * r.cell_mm)
            .collect();
        (run.exit_centroid_mm[0], along_x, along_y, r.cell_mm)
    }

    /// `c = t_i . x_hat` of a plane lit at `deg` from the -x side, seen from straight above,
    /// from the surface geometry code with the exit-point view (the truth has no view term).
    fn shift_along_x(deg: f64) -> f64 {
        use crate::surface::{ViewRay, shift_per_depth};
        use nalgebra::Vector3;
        let a = deg.to_radians();
        let light = Vector3::new(-a.sin(), 0.0, a.cos()) * 1000.0;
        let camera = Vector3::new(0.0, 0.0, 1000.0);
        let s = shift_per_depth(
            &Vector3::zeros(),
            &Vector3::z(),
            &light,
            &camera,
            1.4,
            ViewRay::ExitPoint,
        )
        .unwrap();
        s.x
    }

    fn mc_profile(values: &[f64], cell: f64, mirror: bool, c: f64) -> Profile {
        let n = values.len() as f64;
        Profile {
            noise: None,
            samples: values
                .iter()
                .enumerate()
                .map(|(j, &y)| {
                    let x = (j as f64 + 0.5 - n / 2.0) * cell;
                    Sample {
                        s: if mirror { -x } else { x },
                        y,
                    }
                })
                .collect(),
            slit_width: cell,
            period: None,
            shift_per_depth: c,
        }
    }

    #[test]
    fn layers_fitted_to_monte_carlo_profiles_predict_its_forward_shift_at_a_new_angle() {
        // Training: lights at 30 and 60 degrees, one from each side, profiles along both axes.
        let mut set = Vec::new();
        for (deg, mirror) in [(30.0, false), (60.0, true)] {
            let (_, along_x, along_y, cell) = monte_carlo(deg);
            let c = shift_along_x(deg);
            set.push(mc_profile(
                &along_x,
                cell,
                mirror,
                if mirror { -c } else { c },
            ));
            set.push(mc_profile(&along_y, cell, false, 0.0));
        }
        let est = pooled_spacing(&[set.clone()], 0.1, 2.0, &em()).unwrap();
        let fit = em_layered::fit_layered(&set, DepthSpacing::Fixed(est.spacing_mm), &em(), None)
            .unwrap();
        let mean_depth: f64 = fit
            .layers
            .iter()
            .map(|l| l.weight * l.depth_index as f64 * est.spacing_mm)
            .sum();
        // Held out: 45 degrees. The model's profile centroid is mean depth x c.
        let (truth, ..) = monte_carlo(45.0);
        let predicted = mean_depth * shift_along_x(45.0);
        eprintln!("{est:?}: centroid at 45 deg {predicted:.3} mm, Monte Carlo {truth:.3} mm");
        assert!(
            truth > 0.2,
            "the Monte Carlo moves the light forward: {truth}"
        );
        assert!(
            (predicted / truth - 1.0).abs() < 0.15,
            "predicted forward shift {predicted} mm vs Monte Carlo {truth} mm"
        );
    }
}
