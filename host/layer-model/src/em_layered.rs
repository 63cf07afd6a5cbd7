//! EM with layered means (ours, the default): component `l` is the layer at depth
//! `z_l = l * D` (l = 0 is the surface layer), and its mean in profile `p` is tied to the pixel's
//! light and view geometry, `mu_pl = z_l * c_p` with `c_p = (t_i + t_o) . s_hat_p` (see
//! [`super::surface`]). Weights and sigmas per layer are shared by all profiles of the pixel
//! (3 training projectors x 2 slit axes), so one fit explains every light direction and transfers
//! to a new one by construction.
//!
//! `D` is either fixed (the pipeline estimates it once for the whole subject, see
//! [`super::layer_depth`]) or estimated inside the fit by a conditional M-step (ECM: the
//! auxiliary function is quadratic in `D`, clamped to `[0, max]`).

use super::mixture::{self, Data, EmConfig, EmError, MeanModel, Profile, State, Stats, Trace};

/// One fitted layer.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Layer {
    /// Depth index: the layer lies at `depth_index * D`.
    pub depth_index: usize,
    /// Mixing weight (fractions sum to 1 over the layers).
    pub weight: f64,
    /// Standard deviation in the layer plane (mm).
    pub sigma: f64,
}

/// How the layer spacing is treated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DepthSpacing {
    /// Known (mm).
    Fixed(f64),
    /// Estimated in the fit, starting from this value (mm), at most `max` mm.
    Estimate { start: f64, max: f64 },
}

/// Result of a layered fit.
#[derive(Debug, Clone, PartialEq)]
pub struct LayeredFit {
    /// Layers that survived pruning and model selection, by depth.
    pub layers: Vec<Layer>,
    /// Layer spacing `D` (mm).
    pub depth_spacing: f64,
    /// Integrated radiance of each profile (radiance x mm).
    pub flux: Vec<f64>,
    /// Final log-likelihood per unit weight, averaged over profiles.
    pub log_likelihood: f64,
    pub trace: Trace,
}

#[derive(Debug)]
struct LayerMeans {
    depth_index: Vec<usize>,
    spacing: f64,
    /// `Some(max)` when the spacing is estimated.
    estimate: Option<f64>,
}

/// By hand for `clone_from`, which reuses the vector (the EM keeps a copy of its state at
/// every step).
impl Clone for LayerMeans {
    fn clone(&self) -> Self {
        Self {
            depth_index: self.depth_index.clone(),
            spacing: self.spacing,
            estimate: self.estimate,
        }
    }

    fn clone_from(&mut self, source: &Self) {
        self.depth_index.clone_from(&source.depth_index);
        self.spacing = source.spacing;
        self.estimate = source.estimate;
    }
}

impl MeanModel for LayerMeans {
    fn mean(&self, profiles: &[Profile], p: usize, l: usize) -> f64 {
        self.depth_index[l] as f64 * self.spacing * profiles[p].shift_per_depth
    }

    fn update(&mut self, profiles: &[Profile], stats: &Stats, sigmas: &[f64]) {
        let Some(max) = self.estimate else { return };
        let (num, den) = spacing_normal_equations(&self.depth_index, profiles, stats, sigmas);
        if den > 1e-300 {
            self.spacing = (num / den).clamp(0.0, max);
        }
    }

    fn remove(&mut self, l: usize) {
        self.depth_index.remove(l);
    }

    fn parameter_count(&self, _components: usize) -> usize {
        usize::from(self.estimate.is_some())
    }

    /// The spacing when it is estimated (a fixed one does not move).
    fn free_parameters(&self) -> Vec<f64> {
        self.estimate.map(|_| self.spacing).into_iter().collect()
    }

    fn set_free_parameters(&mut self, values: &[f64]) {
        if let (Some(max), Some(&d)) = (self.estimate, values.first())
            && d.is_finite()
        {
            self.spacing = d.clamp(0.0, max);
        }
    }
}

/// The conditional M-step of the spacing as normal equations `D = num / den`: maximising
/// `sum_l sum_p -E[(x - z_l c_p)^2] / (2 sigma_l^2)` over `D` (with `z_l = index_l D`) is a
/// weighted least squares. Sums of several pixels' equations give the ECM step of a spacing
/// shared by all of them (`subsurface::layer_depth`).
fn spacing_normal_equations(
    depth_index: &[usize],
    profiles: &[Profile],
    stats: &Stats,
    sigmas: &[f64],
) -> (f64, f64) {
    let (mut num, mut den) = (0.0, 0.0);
    for (l, &sigma) in sigmas.iter().enumerate() {
        let z = depth_index[l] as f64;
        let inv_var = 1.0 / (sigma * sigma);
        for (p, prof) in profiles.iter().enumerate() {
            let i = stats.at(p, l);
            let c = z * prof.shift_per_depth;
            num += inv_var * c * stats.sx[i];
            den += inv_var * c * c * stats.n[i];
        }
    }
    (num, den)
}

/// `spacing_normal_equations` of `profiles` at `params` (one E-step): `(num, den)`, with
/// `num / den` the spacing that `params`' weights and sigmas prefer for this pixel alone
/// (unclamped: negative when its profiles lean toward the light).
pub fn spacing_moments(
    profiles: &[Profile],
    params: &LayeredParams,
    wrap_images: usize,
) -> Result<(f64, f64), EmError> {
    let data = Data::new(profiles)?;
    let state = params_state(params);
    let mut stats = Stats::new(profiles.len(), state.weights.len());
    mixture::e_step(&data, &state, wrap_images, Some(&mut stats));
    Ok(spacing_normal_equations(
        &state.means.depth_index,
        profiles,
        &stats,
        &state.sigmas,
    ))
}

fn params_state(params: &LayeredParams) -> State<LayerMeans> {
    State {
        weights: params.layers.iter().map(|l| l.weight).collect(),
        sigmas: params.layers.iter().map(|l| l.sigma).collect(),
        means: LayerMeans {
            depth_index: params.layers.iter().map(|l| l.depth_index).collect(),
            spacing: params.depth_spacing,
            estimate: None,
        },
    }
}

/// A layered model given its parameters, for warm starts and likelihood comparisons.
#[derive(Debug, Clone, PartialEq)]
pub struct LayeredParams {
    pub layers: Vec<Layer>,
    pub depth_spacing: f64,
}

fn initial_state(data: &Data, cfg: &EmConfig, spacing: DepthSpacing) -> State<LayerMeans> {
    // Spread of the pooled profiles sets the range of initial sigmas (shallow narrow, deep wide).
    let (mut m, mut m2, mut wsum) = (0.0, 0.0, 0.0);
    for (prof, w) in data.profiles.iter().zip(&data.weights) {
        for (s, &w) in prof.samples.iter().zip(w) {
            m += w * s.s;
            m2 += w * s.s * s.s;
            wsum += w;
        }
    }
    let spread = if wsum > 0.0 {
        (m2 / wsum - (m / wsum).powi(2)).max(0.0).sqrt()
    } else {
        1.0
    };
    let k = cfg.components;
    let sigmas = (0..k)
        .map(|l| (spread * (l as f64 + 1.0) / k as f64).clamp(cfg.sigma_floor, cfg.sigma_ceiling))
        .collect();
    let (start, estimate) = match spacing {
        DepthSpacing::Fixed(d) => (d, None),
        DepthSpacing::Estimate { start, max } => (start, Some(max)),
    };
    State {
        weights: vec![1.0 / k as f64; k],
        sigmas,
        means: LayerMeans {
            depth_index: (0..k).collect(),
            spacing: start,
            estimate,
        },
    }
}

/// Fits the layered model jointly to all `profiles` of one pixel (one channel).
pub fn fit_layered(
    profiles: &[Profile],
    spacing: DepthSpacing,
    cfg: &EmConfig,
    warm: Option<&LayeredParams>,
) -> Result<LayeredFit, EmError> {
    cfg.validate()?;
    let data = Data::new(profiles)?;
    let state = match warm {
        Some(w) if !w.layers.is_empty() => {
            let raw: Vec<f64> = w.layers.iter().map(|l| l.weight.max(0.0)).collect();
            let estimate = match spacing {
                DepthSpacing::Fixed(_) => None,
                DepthSpacing::Estimate { max, .. } => Some(max),
            };
            State {
                weights: mixture::water_fill(
                    &raw,
                    cfg.weight_floor.min(0.5 / w.layers.len() as f64),
                ),
                sigmas: w
                    .layers
                    .iter()
                    .map(|l| l.sigma.clamp(cfg.sigma_floor, cfg.sigma_ceiling))
                    .collect(),
                means: LayerMeans {
                    depth_index: w.layers.iter().map(|l| l.depth_index).collect(),
                    spacing: match spacing {
                        DepthSpacing::Fixed(d) => d,
                        DepthSpacing::Estimate { .. } => w.depth_spacing,
                    },
                    estimate,
                },
            }
        }
        _ => initial_state(&data, cfg, spacing),
    };
    let (state, ll, trace) = mixture::fit(&data, state, cfg);
    let layers = (0..state.weights.len())
        .map(|l| Layer {
            depth_index: state.means.depth_index[l],
            weight: state.weights[l],
            sigma: state.sigmas[l],
        })
        .collect();
    Ok(LayeredFit {
        layers,
        depth_spacing: state.means.spacing,
        flux: profiles.iter().map(Profile::flux).collect(),
        log_likelihood: ll,
        trace,
    })
}

/// Log-likelihood (per unit weight, averaged over profiles) of `profiles` under a layered model.
pub fn log_likelihood(
    profiles: &[Profile],
    params: &LayeredParams,
    wrap_images: usize,
) -> Result<f64, EmError> {
    let data = Data::new(profiles)?;
    let state = params_state(params);
    Ok(mixture::e_step(&data, &state, wrap_images, None))
}
