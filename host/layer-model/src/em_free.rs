//! EM with free means (the paper): a mixture of box-convolved Gaussians fitted to one profile;
//! components are ordered by mean afterwards to assign them to layers.

use super::mixture::{self, Data, EmConfig, EmError, MeanModel, Profile, State, Stats, Trace};

/// One fitted component.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Component {
    /// Mixing weight (fractions sum to 1 over the components).
    pub weight: f64,
    /// Mean along the profile axis (mm).
    pub mean: f64,
    /// Standard deviation (mm).
    pub sigma: f64,
}

/// Result of a free-means fit.
#[derive(Debug, Clone, PartialEq)]
pub struct FreeFit {
    /// Components ordered by mean.
    pub components: Vec<Component>,
    /// Integrated radiance of the profile (radiance x mm); `flux * weight` is a component's share.
    pub flux: f64,
    /// Final log-likelihood per unit sample weight.
    pub log_likelihood: f64,
    pub trace: Trace,
}

#[derive(Debug)]
struct FreeMeans(Vec<f64>);

/// By hand for `clone_from`, which reuses the vector (the EM keeps a copy of its state at
/// every step).
impl Clone for FreeMeans {
    fn clone(&self) -> Self {
        Self(self.0.clone())
    }

    fn clone_from(&mut self, source: &Self) {
        self.0.clone_from(&source.0);
    }
}

impl MeanModel for FreeMeans {
    fn mean(&self, _profiles: &[Profile], _p: usize, l: usize) -> f64 {
        self.0[l]
    }

    fn update(&mut self, profiles: &[Profile], stats: &Stats, _sigmas: &[f64]) {
        for (l, mean) in self.0.iter_mut().enumerate() {
            let (n, sx) = (0..profiles.len()).fold((0.0, 0.0), |(n, sx), p| {
                let i = stats.at(p, l);
                (n + stats.n[i], sx + stats.sx[i])
            });
            if n > 1e-300 {
                *mean = sx / n;
            }
        }
    }

    fn remove(&mut self, l: usize) {
        self.0.remove(l);
    }

    fn parameter_count(&self, components: usize) -> usize {
        components
    }

    fn free_parameters(&self) -> Vec<f64> {
        self.0.clone()
    }

    fn set_free_parameters(&mut self, values: &[f64]) {
        for (mean, &v) in self.0.iter_mut().zip(values) {
            if v.is_finite() {
                *mean = v;
            }
        }
    }
}

/// Weighted quantile of the sample positions.
fn weighted_quantile(profile: &Profile, weights: &[f64], q: f64) -> f64 {
    let mut order: Vec<usize> = (0..profile.samples.len()).collect();
    order.sort_by(|&a, &b| profile.samples[a].s.total_cmp(&profile.samples[b].s));
    let mut acc = 0.0;
    for &i in &order {
        acc += weights[i];
        if acc >= q {
            return profile.samples[i].s;
        }
    }
    order
        .last()
        .map(|&i| profile.samples[i].s)
        .unwrap_or_default()
}

/// Initial state: means at evenly spaced weighted quantiles, a common sigma, equal weights.
fn initial_state(data: &Data, cfg: &EmConfig) -> State<FreeMeans> {
    let profile = &data.profiles[0];
    let w = &data.weights[0];
    let mean: f64 = profile.samples.iter().zip(w).map(|(s, w)| s.s * w).sum();
    let var: f64 = profile
        .samples
        .iter()
        .zip(w)
        .map(|(s, w)| w * (s.s - mean).powi(2))
        .sum();
    let k = cfg.components;
    let sigma = var
        .sqrt()
        .max(profile.slit_width)
        .clamp(cfg.sigma_floor, cfg.sigma_ceiling);
    let means = (0..k)
        .map(|l| weighted_quantile(profile, w, (l as f64 + 0.5) / k as f64))
        .collect();
    State {
        weights: vec![1.0 / k as f64; k],
        sigmas: vec![sigma; k],
        means: FreeMeans(means),
    }
}

/// Fits a mixture with free means to one profile. `warm` (e.g. a neighbour's fit) replaces the
/// default initialisation; its weights are renormalised and raised to the floor.
pub fn fit_free(
    profile: &Profile,
    cfg: &EmConfig,
    warm: Option<&[Component]>,
) -> Result<FreeFit, EmError> {
    cfg.validate()?;
    let profiles = std::slice::from_ref(profile);
    let data = Data::new(profiles)?;
    let state = match warm {
        Some(c) if !c.is_empty() => {
            let raw: Vec<f64> = c.iter().map(|c| c.weight.max(0.0)).collect();
            State {
                weights: mixture::water_fill(&raw, cfg.weight_floor.min(0.5 / c.len() as f64)),
                sigmas: c
                    .iter()
                    .map(|c| c.sigma.clamp(cfg.sigma_floor, cfg.sigma_ceiling))
                    .collect(),
                means: FreeMeans(c.iter().map(|c| c.mean).collect()),
            }
        }
        _ => initial_state(&data, cfg),
    };
    let (state, ll, trace) = mixture::fit(&data, state, cfg);
    let mut components: Vec<Component> = (0..state.weights.len())
        .map(|l| Component {
            weight: state.weights[l],
            mean: state.means.0[l],
            sigma: state.sigmas[l],
        })
        .collect();
    components.sort_by(|a, b| a.mean.total_cmp(&b.mean));
    Ok(FreeFit {
        components,
        flux: profile.flux(),
        log_likelihood: ll,
        trace,
    })
}

/// Log-likelihood (per unit weight) of a profile under given components: for comparing fits.
pub fn log_likelihood(
    profile: &Profile,
    components: &[Component],
    wrap_images: usize,
) -> Result<f64, EmError> {
    let profiles = std::slice::from_ref(profile);
    let data = Data::new(profiles)?;
    let state = State {
        weights: components.iter().map(|c| c.weight).collect(),
        sigmas: components.iter().map(|c| c.sigma).collect(),
        means: FreeMeans(components.iter().map(|c| c.mean).collect()),
    };
    Ok(mixture::e_step(&data, &state, wrap_images, None))
}
