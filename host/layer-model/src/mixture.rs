//! The EM engine shared by the free-means (paper) and layered-means (ours) fits: a mixture of
//! box-convolved Gaussians (see [`boxed_gaussian`](super::boxed_gaussian)) on weighted 1-D samples.
//!
//! Conventions
//! - A profile is a list of samples `(s, y)`: `s` is the signed distance in mm on the surface from
//!   the centre of the nearest lit slit, `y >= 0` the global radiance measured there (negative
//!   readings from noise are clamped to 0). The slit width `W` (mm) is a known box.
//! - Samples are treated as weighted observations: the log-likelihood of a profile is
//!   `sum_j y_j ln f(s_j) / sum_j y_j` (normalised per profile, so every profile of a joint fit
//!   counts equally whatever its irradiance). Absolute layer weights come back through the flux.
//! - With a slit period `T` (mm) the sweep lights a comb of slits, so a pixel also sees the tails
//!   of the neighbouring slits: each component is wrapped with its images at `+-T`.
//!
//! Guard rails (all keep the EM monotone, because each is the exact maximiser of the EM
//! auxiliary function under a constraint, or a move accepted only if the likelihood does not drop):
//! sigma floor and ceiling (the auxiliary function is unimodal in sigma^2, so clamping is the
//! constrained maximum), weight floor by water-filling (the exact constrained maximum of
//! `sum n_l ln pi_l`), pruning of floor-weight components only when removal does not lower the
//! likelihood. Model selection by BIC is a separate, explicit step that may lower it.

use mlsss_core::capture::FrameNoise;

use super::boxed_gaussian::{BoxedGaussian, Edge, box_edges, edges_into};

/// Errors of the EM fits.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum EmError {
    /// No profile carries any positive radiance: nothing to fit (unlit or shadowed pixel).
    #[error("the profile carries no light (all samples <= 0)")]
    NoSignal,
    /// A sample position or value is NaN or infinite.
    #[error("sample {index} of profile {profile} is not finite (s = {s}, y = {y})")]
    NonFiniteSample {
        profile: usize,
        index: usize,
        s: f64,
        y: f64,
    },
    /// The slit width must be positive and finite.
    #[error("slit width of profile {profile} is {width} mm; it must be > 0")]
    BadSlitWidth { profile: usize, width: f64 },
    /// The configuration is inconsistent (e.g. weight floor times components >= 1).
    #[error("invalid EM configuration: {0}")]
    BadConfig(&'static str),
}

/// One weighted observation of a profile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// Signed distance from the slit centre along the profile axis (mm on the surface).
    pub s: f64,
    /// Global radiance (linear, frame units).
    pub y: f64,
}

/// One 1-D radiance profile with what the model needs to know about how it was lit and seen.
#[derive(Debug, Clone, PartialEq)]
pub struct Profile {
    pub samples: Vec<Sample>,
    /// Slit width on the surface (mm).
    pub slit_width: f64,
    /// Slit period on the surface (mm), if the sweep is a comb (it is in the booth).
    pub period: Option<f64>,
    /// Lateral shift of layer means per mm of depth along this profile's axis,
    /// `(t_i + t_o) . s_hat` (see `em_layered`); unused by the free fit.
    pub shift_per_depth: f64,
    /// Camera noise of the samples, when known: the fits weigh each profile by the information
    /// it carries ([`Profile::information`]); `None` weighs every profile alike.
    pub noise: Option<FrameNoise>,
}

impl Profile {
    /// Sum of the clamped sample values.
    pub fn total(&self) -> f64 {
        self.samples.iter().map(|s| s.y.max(0.0)).sum()
    }

    /// Effective number of photons behind the profile's shape, `total^2 / sum(variance)`: under
    /// Poisson noise a profile of `N` photons has `N` times the log-likelihood of one photon, so
    /// a profile's samples count in proportion to it; read noise lowers it for dim profiles.
    /// `None` without a noise model or signal.
    pub fn information(&self) -> Option<f64> {
        let noise = self.noise?;
        let total = self.total();
        let variance: f64 = self.samples.iter().map(|s| noise.variance(s.y)).sum();
        (total > 0.0 && variance > 0.0 && variance.is_finite()).then(|| total * total / variance)
    }

    /// Integrated flux (radiance x mm) over one period, from the mean sample value; with no period
    /// the trapezoid over the sorted samples.
    pub fn flux(&self) -> f64 {
        let n = self.samples.len();
        if n == 0 {
            return 0.0;
        }
        match self.period {
            Some(t) => self.total() / n as f64 * t,
            None => {
                let mut sorted: Vec<Sample> = self.samples.clone();
                sorted.sort_by(|a, b| a.s.total_cmp(&b.s));
                sorted
                    .windows(2)
                    .map(|w| 0.5 * (w[0].y.max(0.0) + w[1].y.max(0.0)) * (w[1].s - w[0].s))
                    .sum()
            }
        }
    }
}

/// Knobs of the EM.
#[derive(Debug, Clone, PartialEq)]
pub struct EmConfig {
    /// Number of components at the start (the paper: 20).
    pub components: usize,
    /// Hard cap on EM iterations.
    pub max_iterations: usize,
    /// Stop when the log-likelihood gains less than this (absolute, per unit weight) in one step.
    pub tolerance: f64,
    /// Smallest sigma (mm).
    pub sigma_floor: f64,
    /// Largest sigma (mm); profiles are only seen over about one period.
    pub sigma_ceiling: f64,
    /// Smallest mixing weight (water-filling floor).
    pub weight_floor: f64,
    /// Try to remove floor-weight components (accepted only if the likelihood does not drop).
    pub prune: bool,
    /// Reduce the number of components while the BIC improves.
    pub bic: bool,
    /// Observations one sample reading stands for in the BIC (about the photo-electrons behind
    /// a mid-scale reading of a 12-bit camera); profiles are weighted readings, not counts.
    pub bic_counts_per_sample: f64,
    /// EM iterations allowed when refitting a reduced model during model selection.
    pub bic_iterations: usize,
    /// Model selection never goes below this many components (at least 1). The pipeline's
    /// layered fits keep 2: on the full-size head none of 47 242 trials of a single layer won
    /// (they took 178 000 of the fit's 940 000 E-steps, 0.6-0.8 CPU-s of 5.8).
    pub bic_min_components: usize,
    /// Number of slit images on each side of a component (0 = ignore the comb).
    pub wrap_images: usize,
    /// Accelerate the EM by squared extrapolation (SQUAREM, see `converge_squarem`): fewer
    /// E-steps to the same tolerance where the plain EM crawls. Off by default, so the free fit
    /// (the paper's) and everything built on the default stay the plain EM.
    pub squarem: bool,
}

impl Default for EmConfig {
    fn default() -> Self {
        Self {
            components: 20,
            max_iterations: 200,
            tolerance: 1e-7,
            sigma_floor: 0.02,
            sigma_ceiling: 20.0,
            weight_floor: 1e-4,
            prune: true,
            bic: true,
            bic_counts_per_sample: 1000.0,
            bic_iterations: 30,
            bic_min_components: 1,
            wrap_images: 1,
            squarem: false,
        }
    }
}

impl EmConfig {
    pub(crate) fn validate(&self) -> Result<(), EmError> {
        if self.components == 0 {
            return Err(EmError::BadConfig("components must be >= 1"));
        }
        if !(self.weight_floor >= 0.0 && self.weight_floor * (self.components as f64) < 1.0) {
            return Err(EmError::BadConfig(
                "weight_floor * components must be in [0, 1)",
            ));
        }
        if !(self.sigma_floor > 0.0 && self.sigma_ceiling > self.sigma_floor) {
            return Err(EmError::BadConfig("need 0 < sigma_floor < sigma_ceiling"));
        }
        Ok(())
    }
}

/// What one entry of the trace was.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StepKind {
    /// The log-likelihood of the initial parameters.
    Start,
    /// One EM (ECM) iteration: must never lower the log-likelihood.
    Em,
    /// Removal of a floor-weight component: accepted only if it does not lower it.
    Prune,
    /// A model-selection reduction (BIC): a smaller model, may lower it.
    ModelSelection,
    /// An EM step that lowered the log-likelihood beyond rounding (value recorded) and was undone.
    /// Exact EM never does this; the tests assert it never happens.
    Rejected,
    /// A SQUAREM extrapolation (`converge_squarem`): recorded only when it did not lower the
    /// log-likelihood (a worse one is dropped, not recorded).
    Accelerated,
}

/// The log-likelihood after every step of a fit.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Trace {
    pub steps: Vec<(StepKind, f64)>,
}

impl Trace {
    /// Largest drop of the log-likelihood over an EM or prune step (0 if none dropped).
    pub fn worst_drop(&self) -> f64 {
        let kept: Vec<(StepKind, f64)> = self
            .steps
            .iter()
            .copied()
            .filter(|s| s.0 != StepKind::Rejected)
            .collect();
        kept.windows(2)
            .filter(|w| {
                matches!(
                    w[1].0,
                    StepKind::Em | StepKind::Prune | StepKind::Accelerated
                )
            })
            .map(|w| (w[0].1 - w[1].1).max(0.0))
            .fold(0.0, f64::max)
    }

    /// Number of EM steps that were undone because they lowered the log-likelihood.
    pub fn rejected(&self) -> usize {
        self.steps
            .iter()
            .filter(|s| s.0 == StepKind::Rejected)
            .count()
    }

    /// Number of EM iterations run (E-steps of kept parameters: plain and accelerated).
    pub fn iterations(&self) -> usize {
        self.steps
            .iter()
            .filter(|s| matches!(s.0, StepKind::Em | StepKind::Accelerated))
            .count()
    }
}

/// How the component means depend on the profile: free (one mean per component) or tied to a
/// layer depth. Implemented by `em_free` and `em_layered`.
pub(crate) trait MeanModel: Clone {
    /// Mean (mm) of component `l` in profile `p`.
    fn mean(&self, profiles: &[Profile], p: usize, l: usize) -> f64;
    /// Conditional M-step of the means given the sufficient statistics and the current sigmas.
    fn update(&mut self, profiles: &[Profile], stats: &Stats, sigmas: &[f64]);
    /// Forget component `l`.
    fn remove(&mut self, l: usize);
    /// Free mean parameters per component (for BIC) and shared ones.
    fn parameter_count(&self, components: usize) -> usize;
    /// The mean parameters the M-step moves, for SQUAREM's extrapolation (none by default).
    fn free_parameters(&self) -> Vec<f64> {
        Vec::new()
    }
    /// Sets the parameters of [`MeanModel::free_parameters`] (projected onto their bounds).
    fn set_free_parameters(&mut self, _values: &[f64]) {}
}

/// Sufficient statistics of one E-step, per profile `p` and component `l` (flattened `p * K + l`):
/// `n = sum y r`, `sx = sum y r E[x]`, `sxx = sum y r E[x^2]` with `x` the latent position relative
/// to the component's own slit image.
#[derive(Debug, Clone)]
pub(crate) struct Stats {
    pub components: usize,
    pub n: Vec<f64>,
    pub sx: Vec<f64>,
    pub sxx: Vec<f64>,
}

impl Stats {
    pub(crate) fn new(profiles: usize, components: usize) -> Self {
        let len = profiles * components;
        Self {
            components,
            n: vec![0.0; len],
            sx: vec![0.0; len],
            sxx: vec![0.0; len],
        }
    }

    /// All zero again, sized for `profiles x components` (reuses the vectors).
    pub(crate) fn reset(&mut self, profiles: usize, components: usize) {
        let len = profiles * components;
        self.components = components;
        for v in [&mut self.n, &mut self.sx, &mut self.sxx] {
            v.clear();
            v.resize(len, 0.0);
        }
    }

    pub fn at(&self, p: usize, l: usize) -> usize {
        p * self.components + l
    }
}

/// Mixture state: weights and sigmas per component; means come from the mean model.
#[derive(Debug)]
pub(crate) struct State<M: MeanModel> {
    pub weights: Vec<f64>,
    pub sigmas: Vec<f64>,
    pub means: M,
}

/// By hand for `clone_from`, which reuses the vectors: every plain EM step keeps a copy of the
/// state it started from (to undo a step that rounding made worse).
impl<M: MeanModel> Clone for State<M> {
    fn clone(&self) -> Self {
        Self {
            weights: self.weights.clone(),
            sigmas: self.sigmas.clone(),
            means: self.means.clone(),
        }
    }

    fn clone_from(&mut self, source: &Self) {
        self.weights.clone_from(&source.weights);
        self.sigmas.clone_from(&source.sigmas);
        self.means.clone_from(&source.means);
    }
}

/// Prepared data: validated, clamped, normalised per profile.
pub(crate) struct Data<'a> {
    pub profiles: &'a [Profile],
    /// Sample weights per profile: `y / total` times the profile's [`relative_information`]
    /// (they sum to that over a profile with signal; empty otherwise).
    pub weights: Vec<Vec<f64>>,
    /// Per profile, its samples with weight in order of position (for
    /// [`box_edges`](super::boxed_gaussian::box_edges)). Sorted once here: the samples do not
    /// move between E-steps, which sorted them every time.
    pub orders: Vec<Vec<usize>>,
    pub samples: usize,
}

impl<'a> Data<'a> {
    pub fn new(profiles: &'a [Profile]) -> Result<Self, EmError> {
        let mut weights = Vec::with_capacity(profiles.len());
        let mut samples = 0;
        for (p, prof) in profiles.iter().enumerate() {
            if !(prof.slit_width > 0.0 && prof.slit_width.is_finite()) {
                return Err(EmError::BadSlitWidth {
                    profile: p,
                    width: prof.slit_width,
                });
            }
            for (index, s) in prof.samples.iter().enumerate() {
                if !(s.s.is_finite() && s.y.is_finite()) {
                    return Err(EmError::NonFiniteSample {
                        profile: p,
                        index,
                        s: s.s,
                        y: s.y,
                    });
                }
            }
        }
        let trust = relative_information(profiles.iter());
        for (prof, trust) in profiles.iter().zip(trust) {
            let total = prof.total();
            if total > 0.0 {
                weights.push(
                    prof.samples
                        .iter()
                        .map(|s| trust * s.y.max(0.0) / total)
                        .collect(),
                );
                samples += prof.samples.len();
            } else {
                weights.push(Vec::new());
            }
        }
        if samples == 0 {
            return Err(EmError::NoSignal);
        }
        let orders = profiles
            .iter()
            .zip(&weights)
            .map(|(prof, w)| by_position(prof, w))
            .collect();
        Ok(Self {
            profiles,
            weights,
            orders,
            samples,
        })
    }

    fn profiles_with_signal(&self) -> usize {
        self.weights.iter().filter(|w| !w.is_empty()).count()
    }
}

/// The samples of `prof` with positive weight in `weights`, in order of position (none when
/// `weights` is empty: a profile without signal).
pub(crate) fn by_position(prof: &Profile, weights: &[f64]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..weights.len()).filter(|&j| weights[j] > 0.0).collect();
    order.sort_by(|&a, &b| prof.samples[a].s.total_cmp(&prof.samples[b].s));
    order
}

/// Per profile, the weight of its samples in a pooled likelihood: its
/// [`Profile::information`] relative to the mean over the profiles with signal (so the weights
/// average 1 and a likelihood averaged over profiles keeps its scale), or 1 for every profile
/// when any of them has no noise model. 0 for a profile without signal.
pub(crate) fn relative_information<'p>(profiles: impl Iterator<Item = &'p Profile>) -> Vec<f64> {
    let profiles: Vec<&Profile> = profiles.collect();
    let has_signal = |p: &Profile| p.total() > 0.0;
    // The information of each profile with signal, in order; `None` when one has no noise model.
    let information: Option<Vec<f64>> = profiles
        .iter()
        .filter(|p| has_signal(p))
        .map(|p| p.information())
        .collect();
    let mean = information
        .as_ref()
        .filter(|info| !info.is_empty())
        .map(|info| info.iter().sum::<f64>() / info.len() as f64)
        .filter(|m| *m > 0.0 && m.is_finite());
    let mut relative = information.into_iter().flatten();
    profiles
        .iter()
        .map(|p| match (has_signal(p), mean) {
            (false, _) => 0.0,
            (true, Some(mean)) => relative.next().map_or(1.0, |i| i / mean),
            (true, None) => 1.0,
        })
        .collect()
}

/// Offsets of the slit images considered for a profile.
fn images(profile: &Profile, wrap: usize) -> impl Iterator<Item = f64> + '_ {
    let w = wrap as i64;
    (-w..=w).filter_map(move |m| match (m, profile.period) {
        (0, _) => Some(0.0),
        (_, Some(t)) => Some(m as f64 * t),
        (_, None) => None,
    })
}

/// Beyond this many sigmas (plus half the slit) an image contributes nothing worth computing.
pub(crate) const NEGLIGIBLE_SIGMAS: f64 = 12.0;

/// Below this a sample's summed density is recomputed in log space (its linear terms may have
/// dropped components beyond [`LINEAR_MIN`] that matter at this scale).
const LINEAR_SUM_MIN: f64 = 1e-200;

/// One term of a sample's mixture: component, joint (density x weight, linear or log), and the
/// posterior mean and variance of the latent position.
type Term = (usize, f64, f64, f64);

/// Log-likelihood (per unit weight, averaged over profiles with signal) and, if `stats` is given,
/// the E-step sufficient statistics.
///
/// Each sample's terms are summed in linear space ([`BoxedGaussian::posterior_linear`], no
/// logarithm or exponential per term); a sample whose summed density is below
/// [`LINEAR_SUM_MIN`] (every component ~37 sigmas away) is redone in log space, which is
/// accurate for any distance.
pub(crate) fn e_step<M: MeanModel>(
    data: &Data,
    state: &State<M>,
    wrap: usize,
    stats: Option<&mut Stats>,
) -> f64 {
    SCRATCH.with(|scratch| match scratch.try_borrow_mut() {
        Ok(mut scratch) => e_step_in(data, state, wrap, stats, &mut scratch),
        // Only a re-entrant call (none today) finds the thread's scratch taken.
        Err(_) => e_step_in(data, state, wrap, stats, &mut EStepScratch::default()),
    })
}

/// What an E-step allocates, kept per thread between E-steps. Why: a pixel-channel fit runs
/// ~50 E-steps, each of which allocated ~35 small vectors (a term list per sample) afresh:
/// about 85 million allocations for the full-size head's ~56 000 fits.
#[derive(Debug, Default)]
struct EStepScratch {
    linear: LinearTerms,
    terms: Vec<Term>,
    /// (component, weight, its boxed Gaussian in this profile): components with weight only.
    components: Vec<(usize, f64, BoxedGaussian)>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<EStepScratch> = std::cell::RefCell::default();
}

fn e_step_in<M: MeanModel>(
    data: &Data,
    state: &State<M>,
    wrap: usize,
    mut stats: Option<&mut Stats>,
    scratch: &mut EStepScratch,
) -> f64 {
    let k = state.weights.len();
    let mut total = 0.0;
    let with_stats = stats.is_some();
    let EStepScratch {
        linear,
        terms,
        components,
    } = scratch;
    for (p, prof) in data.profiles.iter().enumerate() {
        let weights = &data.weights[p];
        if weights.is_empty() {
            continue;
        }
        components.clear();
        components.extend((0..k).filter(|&l| state.weights[l] > 0.0).map(|l| {
            (
                l,
                state.weights[l],
                BoxedGaussian {
                    mean: state.means.mean(data.profiles, p, l),
                    sigma: state.sigmas[l],
                    width: prof.slit_width,
                },
            )
        }));
        linear.fill(components, prof, &data.orders[p], wrap, with_stats);
        let mut ll = 0.0;
        for (j, (sample, &y)) in prof.samples.iter().zip(weights).enumerate() {
            if y <= 0.0 {
                continue;
            }
            let mut sum = linear.sums[j];
            let (ln_sum, sample_terms) = if sum >= LINEAR_SUM_MIN {
                (sum.ln(), linear.terms[j].as_slice())
            } else {
                let (max, shares) = log_terms(components, prof, sample.s, wrap, with_stats, terms);
                sum = shares;
                (max + shares.ln(), terms.as_slice())
            };
            ll += y * ln_sum;
            if let Some(st) = stats.as_deref_mut() {
                let scale = y / sum;
                for &(c, share, mean, var) in sample_terms {
                    let r = scale * share;
                    if r > 0.0 {
                        let i = st.at(p, c);
                        st.n[i] += r;
                        st.sx[i] += r * mean;
                        st.sxx[i] += r * (var + mean * mean);
                    }
                }
            }
        }
        total += ll;
    }
    total / data.profiles_with_signal() as f64
}

/// The linear-space terms of every sample of one profile: per sample, the joints `w h(s)` (and
/// the posterior moments when wanted) of every component and slit image in the order
/// components, then images, and their sum. Each component and image walks the samples in
/// order of position so that neighbouring slit boxes share their common edge ([`box_edges`]);
/// the edges of all the walks are evaluated together ([`edges_into`]), then the boxes visited
/// in the walks' order.
#[derive(Debug, Default)]
struct LinearTerms {
    terms: Vec<Vec<Term>>,
    sums: Vec<f64>,
    /// The standardised edges of the walks, then their evaluation.
    edge_z: Vec<f64>,
    edges: Vec<Edge>,
    /// Every box of the walks in order: (sample, index into the components, lower and upper
    /// edge).
    boxes: Vec<(usize, usize, usize, usize)>,
}

impl LinearTerms {
    /// `order`: the samples with weight, by position ([`Data::orders`]).
    fn fill(
        &mut self,
        components: &[(usize, f64, BoxedGaussian)],
        prof: &Profile,
        order: &[usize],
        wrap: usize,
        with_stats: bool,
    ) {
        let n = prof.samples.len();
        self.terms.resize_with(n, Vec::new);
        self.terms.iter_mut().for_each(Vec::clear);
        self.sums.clear();
        self.sums.resize(n, 0.0);
        self.edge_z.clear();
        self.boxes.clear();
        for (c, (_, _, g)) in components.iter().enumerate() {
            for offset in images(prof, wrap) {
                box_edges(
                    g,
                    offset,
                    order,
                    |j| prof.samples[j].s,
                    |s| image_reaches(g, offset, s),
                    &mut self.edge_z,
                    |j, lower, upper| self.boxes.push((j, c, lower, upper)),
                );
            }
        }
        edges_into(&self.edge_z, &mut self.edges);
        for &(j, c, lower, upper) in &self.boxes {
            let (l, w, ref g) = components[c];
            let (lower, upper) = (&self.edges[lower], &self.edges[upper]);
            if with_stats {
                if let Some(post) = g.posterior_between(lower, upper) {
                    let joint = w * post.density;
                    self.sums[j] += joint;
                    self.terms[j].push((l, joint, post.mean, post.variance));
                }
            } else {
                self.sums[j] += w * g.density_between(lower, upper);
            }
        }
    }
}

/// Whether the slit image at `offset` of component `g` reaches sample `s`: beyond
/// NEGLIGIBLE_SIGMAS an image (never the central one) contributes nothing worth computing. A
/// NaN offset (no such image) reaches nothing.
pub(crate) fn image_reaches(g: &BoxedGaussian, offset: f64, s: f64) -> bool {
    let dist = (s - offset - g.mean).abs() - 0.5 * g.width;
    offset == 0.0 || dist <= NEGLIGIBLE_SIGMAS * g.sigma
}

/// The slit images of `prof` component `g` reaches from sample `s`.
fn images_of<'a>(
    prof: &'a Profile,
    wrap: usize,
    g: &'a BoxedGaussian,
    s: f64,
) -> impl Iterator<Item = f64> + 'a {
    images(prof, wrap).filter(move |&offset| image_reaches(g, offset, s))
}

/// Fills `terms` with the joints of one sample relative to the largest (`exp(ln joint - max)`),
/// computed in log space; returns `max` and the sum of the relative joints.
fn log_terms(
    components: &[(usize, f64, BoxedGaussian)],
    prof: &Profile,
    s: f64,
    wrap: usize,
    with_stats: bool,
    terms: &mut Vec<Term>,
) -> (f64, f64) {
    terms.clear();
    for &(l, w, ref g) in components {
        let ln_w = w.ln();
        for offset in images_of(prof, wrap, g, s) {
            let x = s - offset;
            // The posterior moments only when the statistics are wanted.
            if with_stats {
                let post = g.posterior(x);
                terms.push((l, ln_w + post.ln_density, post.mean, post.variance));
            } else {
                terms.push((l, ln_w + g.ln_density(x), 0.0, 0.0));
            }
        }
    }
    let max = terms.iter().map(|t| t.1).fold(f64::NEG_INFINITY, f64::max);
    let mut sum = 0.0;
    for t in terms.iter_mut() {
        t.1 = (t.1 - max).exp();
        sum += t.1;
    }
    (max, sum)
}

/// Exact maximiser of `sum n_l ln pi_l` over the simplex with `pi_l >= floor`.
pub(crate) fn water_fill(n: &[f64], floor: f64) -> Vec<f64> {
    let k = n.len();
    let mut clamped = vec![false; k];
    loop {
        let free_mass: f64 = (0..k).filter(|&l| !clamped[l]).map(|l| n[l]).sum();
        let clamped_count = clamped.iter().filter(|&&c| c).count();
        let budget = 1.0 - clamped_count as f64 * floor;
        if free_mass <= 0.0 {
            // No responsibility anywhere free: spread the budget evenly.
            let free = k - clamped_count;
            return (0..k)
                .map(|l| {
                    if clamped[l] {
                        floor
                    } else {
                        budget / free.max(1) as f64
                    }
                })
                .collect();
        }
        let mut changed = false;
        for l in 0..k {
            if !clamped[l] && n[l] / free_mass * budget < floor {
                clamped[l] = true;
                changed = true;
            }
        }
        if !changed {
            return (0..k)
                .map(|l| {
                    if clamped[l] {
                        floor
                    } else {
                        n[l] / free_mass * budget
                    }
                })
                .collect();
        }
    }
}

/// The sigma M-step given the (already updated) means: pooled second moment about each profile's
/// mean, clamped to the floor and ceiling. Components without responsibility keep their sigma.
fn update_sigmas<M: MeanModel>(data: &Data, state: &mut State<M>, stats: &Stats, cfg: &EmConfig) {
    for l in 0..state.sigmas.len() {
        let (mut n, mut ss) = (0.0, 0.0);
        for p in 0..data.profiles.len() {
            let i = stats.at(p, l);
            let mu = state.means.mean(data.profiles, p, l);
            n += stats.n[i];
            ss += stats.sxx[i] - 2.0 * mu * stats.sx[i] + mu * mu * stats.n[i];
        }
        if n > 1e-300 {
            let var = (ss / n).max(0.0);
            state.sigmas[l] = var.sqrt().clamp(cfg.sigma_floor, cfg.sigma_ceiling);
        }
    }
}

/// The M-step (ECM order: weights, then means, then sigmas) from one E-step's statistics.
fn m_step<M: MeanModel>(data: &Data, state: &mut State<M>, stats: &Stats, cfg: &EmConfig) {
    let k = state.weights.len();
    let n_per_component: Vec<f64> = (0..k)
        .map(|l| {
            (0..data.profiles.len())
                .map(|p| stats.n[stats.at(p, l)])
                .sum()
        })
        .collect();
    state.weights = water_fill(&n_per_component, cfg.weight_floor);
    state.means.update(data.profiles, stats, &state.sigmas);
    update_sigmas(data, state, stats, cfg);
}

fn remove_component<M: MeanModel>(state: &mut State<M>, l: usize) {
    state.weights.remove(l);
    state.sigmas.remove(l);
    state.means.remove(l);
    let sum: f64 = state.weights.iter().sum();
    if sum > 0.0 {
        state.weights.iter_mut().for_each(|w| *w /= sum);
    }
}

/// EM to convergence from `state`, appending to `trace`. Returns the final log-likelihood.
/// With [`EmConfig::squarem`], [`converge_squarem`]; else the plain EM: one E-step per
/// iteration: it scores the parameters of the previous M-step and gives the
/// statistics of the next.
///
/// `first`: the kind of step the starting log-likelihood is recorded as in `trace` (`None`: not
/// recorded). Why: the first E-step with statistics gives the same log-likelihood as one without
/// (the same sums; only terms below [`LINEAR_MIN`](crate::boxed_gaussian::LINEAR_MIN), which
/// cannot move a sum this far above [`LINEAR_SUM_MIN`], differ), so the start of a fit and of a
/// model-selection trial is recorded from it instead of from an E-step of its own (one E-step
/// of ~25 per fit).
fn converge<M: MeanModel>(
    data: &Data,
    state: &mut State<M>,
    cfg: &EmConfig,
    trace: &mut Trace,
    first: Option<StepKind>,
) -> f64 {
    if cfg.squarem {
        return converge_squarem(data, state, cfg, trace, first);
    }
    let (mut stats, mut ll) = first_e_step(data, state, cfg, trace, first);
    // Two buffers swapped each iteration instead of fresh statistics per E-step.
    let mut spare = Spare::new(data, state);
    for _ in 0..cfg.max_iterations {
        if !plain_step(data, cfg, trace, state, &mut stats, &mut spare, &mut ll) {
            break;
        }
    }
    ll
}

/// The statistics and log-likelihood of `state`'s first E-step, the log-likelihood recorded in
/// `trace` as `first` (see [`converge`]).
fn first_e_step<M: MeanModel>(
    data: &Data,
    state: &State<M>,
    cfg: &EmConfig,
    trace: &mut Trace,
    first: Option<StepKind>,
) -> (Stats, f64) {
    let mut stats = Stats::new(data.profiles.len(), state.weights.len());
    let ll = e_step(data, state, cfg.wrap_images, Some(&mut stats));
    if let Some(kind) = first {
        trace.steps.push((kind, ll));
    }
    (stats, ll)
}

/// The buffers a run of plain EM steps reuses: the other statistics and the state a step
/// started from.
struct Spare<M: MeanModel> {
    stats: Stats,
    state: State<M>,
}

impl<M: MeanModel> Spare<M> {
    fn new(data: &Data, state: &State<M>) -> Self {
        Self {
            stats: Stats::new(data.profiles.len(), state.weights.len()),
            state: state.clone(),
        }
    }
}

/// One plain EM step from `state` (E-step statistics `stats`, log-likelihood `ll`), recorded
/// in `trace`. A step that rounding made worse is undone; a kept one moves `state`, `ll` and
/// `stats` on (`spare.stats` is the other buffer). Returns whether the fit goes on: not after
/// an undone step, nor after one that gained less than the tolerance.
fn plain_step<M: MeanModel>(
    data: &Data,
    cfg: &EmConfig,
    trace: &mut Trace,
    state: &mut State<M>,
    stats: &mut Stats,
    spare: &mut Spare<M>,
    ll: &mut f64,
) -> bool {
    spare.state.clone_from(state);
    m_step(data, state, stats, cfg);
    let next = &mut spare.stats;
    next.reset(data.profiles.len(), state.weights.len());
    let next_ll = e_step(data, state, cfg.wrap_images, Some(next));
    if !keeps(*ll, next_ll) {
        // Rounding made a step worse: keep the better parameters and stop.
        trace.steps.push((StepKind::Rejected, next_ll));
        std::mem::swap(state, &mut spare.state);
        return false;
    }
    trace.steps.push((StepKind::Em, next_ll));
    let gain = next_ll - *ll;
    *ll = next_ll;
    std::mem::swap(stats, next);
    gain >= cfg.tolerance
}

/// Whether a plain EM step from log-likelihood `ll` to `next` is kept: the exact EM never
/// lowers it, so only rounding (or a non-finite value) can, and such a step is undone.
fn keeps(ll: f64, next: f64) -> bool {
    next.is_finite() && next >= ll - 1e-12 * ll.abs().max(1.0)
}

/// Parameters of `state` in the unconstrained coordinates SQUAREM extrapolates in, into `u`:
/// log weights, log sigmas, then the mean model's [`MeanModel::free_parameters`].
fn squarem_coordinates<M: MeanModel>(state: &State<M>, u: &mut Vec<f64>) {
    u.clear();
    u.extend(state.weights.iter().map(|w| w.ln()));
    u.extend(state.sigmas.iter().map(|s| s.ln()));
    u.extend(state.means.free_parameters());
}

/// SQUAREM's step length (scheme S3, `-|r| / |v|` with `r = u1 - u0`, `v = u2 - 2 u1 + u0`),
/// as its magnitude; `None` when there is nothing to extrapolate (no curvature, a non-finite
/// coordinate, or a step of at most 1: a step of 1 is `u2` itself).
fn squarem_step(u: [&[f64]; 3]) -> Option<f64> {
    let (mut rr, mut vv) = (0.0, 0.0);
    for ((a, b), c) in u[0].iter().zip(u[1]).zip(u[2]) {
        let r = b - a;
        let v = c - 2.0 * b + a;
        rr += r * r;
        vv += v * v;
    }
    let step = (rr / vv).sqrt();
    (step.is_finite() && step > 1.0).then_some(step)
}

/// The SQUAREM point `u0 + 2 a r + a^2 v` (`a` the step magnitude) mapped back to parameters:
/// weights water-filled to the floor, sigmas clamped, the means projected by their model. The
/// result satisfies every constraint the M-step keeps, so the EM can continue from it.
fn squarem_point<M: MeanModel>(
    like: &State<M>,
    u: [&[f64]; 3],
    step: f64,
    cfg: &EmConfig,
) -> State<M> {
    let x: Vec<f64> = (0..u[0].len())
        .map(|i| {
            let (r, v) = (u[1][i] - u[0][i], u[2][i] - 2.0 * u[1][i] + u[0][i]);
            u[0][i] + 2.0 * step * r + step * step * v
        })
        .collect();
    let k = like.weights.len();
    let mut state = like.clone();
    let raw: Vec<f64> = x[..k].iter().map(|l| l.exp()).collect();
    state.weights = water_fill(&raw, cfg.weight_floor);
    state.sigmas = x[k..2 * k]
        .iter()
        .map(|l| l.exp().clamp(cfg.sigma_floor, cfg.sigma_ceiling))
        .collect();
    state.means.set_free_parameters(&x[2 * k..]);
    state
}

/// [`converge`] accelerated by SQUAREM (Varadhan & Roland 2008, "Simple and globally convergent
/// methods for accelerating the convergence of any EM algorithm", Scand. J. Stat. 35): two plain
/// EM steps `u0 -> u1 -> u2`, then the extrapolated point `u0 + 2 a r + a^2 v` (scheme S3, in
/// log weights and log sigmas), kept only if its log-likelihood is not below `u2`'s, so the
/// trace stays monotone; the next cycle's first plain step starts from it (their stabilising
/// step). The step cap starts at 1 and grows 4x whenever the step reaches it, shrinks 4x when an
/// extrapolation is dropped (their `step.max0 = 1, mstep = 4`).
///
/// Why: the full-size head's fits spent much of their E-steps in long linear crawls (a ninth of
/// its 57 855 main fits ran 31 plain steps or more, up to the cap of 200), which SQUAREM
/// shortens. The stopping rule is the plain EM's, a plain step gaining less than `tolerance`,
/// and `max_iterations` counts every E-step (extrapolations included). [`fit`]'s
/// model-selection trials stay plain (see there).
fn converge_squarem<M: MeanModel>(
    data: &Data,
    state: &mut State<M>,
    cfg: &EmConfig,
    trace: &mut Trace,
    first: Option<StepKind>,
) -> f64 {
    let (mut stats, mut ll) = first_e_step(data, state, cfg, trace, first);
    let mut trial_stats = Stats::new(data.profiles.len(), state.weights.len());
    let mut spare = Spare::new(data, state);
    let mut e_steps = 0;
    let mut max_step = 1.0f64;
    // `path` holds u0 and u1 of the cycle under way (the first `on_path`), then u2; reused
    // from cycle to cycle.
    let mut path: [Vec<f64>; 3] = Default::default();
    let mut on_path = 0;
    while e_steps < cfg.max_iterations {
        if on_path == 2 {
            squarem_coordinates(state, &mut path[2]);
            let u = [path[0].as_slice(), path[1].as_slice(), path[2].as_slice()];
            let raw = squarem_step(u);
            let trial = match raw {
                // A step of 1 is u2 itself: nothing to evaluate, but the cap may grow.
                Some(_) if max_step <= 1.0 => {
                    max_step = 4.0;
                    None
                }
                Some(raw) => Some((raw.min(max_step), raw >= max_step)),
                None => None,
            }
            .map(|(step, capped)| (squarem_point(state, u, step, cfg), capped));
            on_path = 0;
            let Some((trial, capped)) = trial else {
                continue;
            };
            trial_stats.reset(data.profiles.len(), trial.weights.len());
            let trial_ll = e_step(data, &trial, cfg.wrap_images, Some(&mut trial_stats));
            e_steps += 1;
            if trial_ll.is_finite() && trial_ll >= ll {
                trace.steps.push((StepKind::Accelerated, trial_ll));
                *state = trial;
                ll = trial_ll;
                std::mem::swap(&mut stats, &mut trial_stats);
                if capped {
                    max_step *= 4.0;
                }
            } else {
                max_step = (max_step / 4.0).max(1.0);
            }
            continue;
        }
        squarem_coordinates(state, &mut path[on_path]);
        on_path += 1;
        e_steps += 1;
        if !plain_step(data, cfg, trace, state, &mut stats, &mut spare, &mut ll) {
            break;
        }
    }
    ll
}

/// Removes floor-weight components while that does not lower the likelihood.
fn prune<M: MeanModel>(
    data: &Data,
    state: &mut State<M>,
    cfg: &EmConfig,
    ll: f64,
    trace: &mut Trace,
) -> (f64, bool) {
    let mut ll = ll;
    let mut any = false;
    let mut l = 0;
    while l < state.weights.len() && state.weights.len() > 1 {
        if state.weights[l] <= cfg.weight_floor * 1.000_001 {
            let mut trial = state.clone();
            remove_component(&mut trial, l);
            let trial_ll = e_step(data, &trial, cfg.wrap_images, None);
            if trial_ll.is_finite() && trial_ll >= ll {
                *state = trial;
                ll = trial_ll;
                any = true;
                trace.steps.push((StepKind::Prune, ll));
                continue;
            }
        }
        l += 1;
    }
    (ll, any)
}

/// Bayesian information criterion with `samples x bic_counts_per_sample` observations and the
/// normalised log-likelihood scaled back by it (samples are radiance readings, not photon counts).
pub(crate) fn bic<M: MeanModel>(data: &Data, state: &State<M>, ll: f64, cfg: &EmConfig) -> f64 {
    let k = state.weights.len();
    let params = (k - 1) + k + state.means.parameter_count(k);
    let n = data.samples as f64 * cfg.bic_counts_per_sample.max(1.0);
    let total_ll = ll * n / data.profiles_with_signal() as f64;
    -2.0 * total_ll + params as f64 * n.ln()
}

/// A model-selection trial: the plain EM of the reduced model `trial` (at most
/// [`EmConfig::bic_iterations`] steps, to the tolerance), recorded in `trace`; its criterion and
/// log-likelihood when the criterion beats `best`, else `None`.
///
/// The trial's EM is plain even when the fit is accelerated: its cap of `bic_iterations` plain
/// steps is part of the criterion (a fifth of the trials on the full-size head stop at it), and
/// SQUAREM's trials, getting further, dropped more components (2.184 -> 2.132 per fit) and lost
/// 0.04 dB of held-out PSNR.
///
/// A trial is given up as soon as it cannot win: when even its last step's gain, repeated for
/// every step it has left, would not bring the criterion below `best` (the EM's gains shrink as
/// it converges, so this bounds where it ends). Why: nearly every trial loses (on the full-size
/// head 55 893 of 56 900, most fits trying to drop the second of two layers), and the losers'
/// E-steps ran to the tolerance or the cap for nothing: 519 000, 45 % of the fit's E-steps. The
/// bound gives up 40 % of them and, as the trials' traces showed, gave up 7 trials of 56 900
/// that would have won (their gains grew after the bound was taken); the held-out figures
/// moved by at most 0.02 % (full-size head, projector 3 held out).
fn model_selection_trial<M: MeanModel>(
    data: &Data,
    trial: &mut State<M>,
    cfg: &EmConfig,
    trace: &mut Trace,
    best: f64,
) -> Option<(f64, f64)> {
    let short = EmConfig {
        max_iterations: cfg.bic_iterations,
        squarem: false,
        ..cfg.clone()
    };
    let (mut stats, mut ll) =
        first_e_step(data, trial, &short, trace, Some(StepKind::ModelSelection));
    let mut spare = Spare::new(data, trial);
    for step in 0..short.max_iterations {
        let before = ll;
        if !plain_step(data, &short, trace, trial, &mut stats, &mut spare, &mut ll) {
            break;
        }
        // From the second step on (the first one's gain is the removal's readjustment).
        let left = (short.max_iterations - step) as f64;
        if step >= 1 && bic(data, trial, ll + left * (ll - before), cfg) >= best {
            return None;
        }
    }
    let score = bic(data, trial, ll, cfg);
    (score < best).then_some((score, ll))
}

/// The full fit: EM to convergence, pruning, then BIC reductions (dropping the lightest
/// component) while the criterion improves, down to [`EmConfig::bic_min_components`].
pub(crate) fn fit<M: MeanModel>(
    data: &Data,
    mut state: State<M>,
    cfg: &EmConfig,
) -> (State<M>, f64, Trace) {
    let mut trace = Trace::default();
    let mut ll = converge(data, &mut state, cfg, &mut trace, Some(StepKind::Start));
    if cfg.prune {
        let (after, pruned) = prune(data, &mut state, cfg, ll, &mut trace);
        ll = after;
        if pruned {
            ll = converge(data, &mut state, cfg, &mut trace, None);
        }
    }
    if cfg.bic {
        let mut best = bic(data, &state, ll, cfg);
        while state.weights.len() > cfg.bic_min_components.max(1) {
            let lightest = (0..state.weights.len())
                .min_by(|&a, &b| state.weights[a].total_cmp(&state.weights[b]))
                .unwrap_or(0);
            let mut trial = state.clone();
            remove_component(&mut trial, lightest);
            let mut trial_trace = Trace::default();
            let Some((score, trial_ll)) =
                model_selection_trial(data, &mut trial, cfg, &mut trial_trace, best)
            else {
                break;
            };
            best = score;
            state = trial;
            ll = trial_ll;
            trace.steps.extend(trial_trace.steps);
        }
    }
    (state, ll, trace)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Fixed means per component (the test needs no M-step of the means).
    #[derive(Debug, Clone)]
    struct Fixed(Vec<f64>);

    impl MeanModel for Fixed {
        fn mean(&self, _profiles: &[Profile], _p: usize, l: usize) -> f64 {
            self.0[l]
        }
        fn update(&mut self, _profiles: &[Profile], _stats: &Stats, _sigmas: &[f64]) {}
        fn remove(&mut self, l: usize) {
            self.0.remove(l);
        }
        fn parameter_count(&self, components: usize) -> usize {
            components
        }
    }

    /// The E-step with every sample in log space (the form accurate at any distance).
    fn log_space_e_step(data: &Data, state: &State<Fixed>, wrap: usize, st: &mut Stats) -> f64 {
        let mut total = 0.0;
        let mut terms = Vec::new();
        for (p, prof) in data.profiles.iter().enumerate() {
            let components: Vec<(usize, f64, BoxedGaussian)> = (0..state.weights.len())
                .map(|l| {
                    let g = BoxedGaussian {
                        mean: state.means.0[l],
                        sigma: state.sigmas[l],
                        width: prof.slit_width,
                    };
                    (l, state.weights[l], g)
                })
                .collect();
            for (sample, &y) in prof.samples.iter().zip(&data.weights[p]) {
                let (max, sum) = log_terms(&components, prof, sample.s, wrap, true, &mut terms);
                total += y * (max + sum.ln());
                for &(l, share, mean, var) in &terms {
                    let (i, r) = (st.at(p, l), y * share / sum);
                    st.n[i] += r;
                    st.sx[i] += r * mean;
                    st.sxx[i] += r * (var + mean * mean);
                }
            }
        }
        total / data.profiles_with_signal() as f64
    }

    #[test]
    fn linear_e_step_matches_the_log_space_one_near_and_far() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        for trial in 0..40 {
            // Some trials put every sample ~50 sigmas from every component (the log fallback).
            let far = trial % 4 == 0;
            let profiles: Vec<Profile> = (0..3)
                .map(|_| {
                    let period = rng.gen_range(3.0..12.0);
                    Profile {
                        noise: None,
                        samples: (0..10)
                            .map(|j| Sample {
                                s: -0.5 * period + period * (j as f64 + 0.5) / 10.0,
                                y: rng.gen_range(0.0..2.0),
                            })
                            .collect(),
                        slit_width: period / 10.0,
                        period: Some(period),
                        shift_per_depth: 0.0,
                    }
                })
                .collect();
            let data = Data::new(&profiles).unwrap();
            let k = rng.gen_range(1..5);
            let state = State {
                weights: vec![1.0 / k as f64; k],
                sigmas: (0..k)
                    .map(|_| if far { 0.02 } else { rng.gen_range(0.05..6.0) })
                    .collect(),
                means: Fixed(
                    (0..k)
                        .map(|_| if far { 40.0 } else { rng.gen_range(-1.0..1.0) })
                        .collect(),
                ),
            };
            let mut fast = Stats::new(profiles.len(), k);
            let mut reference = Stats::new(profiles.len(), k);
            let ll = e_step(&data, &state, 1, Some(&mut fast));
            let ll_ref = log_space_e_step(&data, &state, 1, &mut reference);
            let ll_only = e_step(&data, &state, 1, None);
            assert!(
                (ll - ll_ref).abs() < 1e-10 * ll_ref.abs().max(1.0),
                "{ll} vs {ll_ref}"
            );
            assert!((ll_only - ll_ref).abs() < 1e-10 * ll_ref.abs().max(1.0));
            for (a, b) in [
                (&fast.n, &reference.n),
                (&fast.sx, &reference.sx),
                (&fast.sxx, &reference.sxx),
            ] {
                for (x, y) in a.iter().zip(b) {
                    assert!((x - y).abs() < 1e-9 * y.abs().max(1.0), "{x} vs {y}");
                }
            }
        }
    }

    /// Profiles of one boxed Gaussian, fitted from three components on its mean: model
    /// selection goes down to one component, or stops at `bic_min_components`.
    #[test]
    fn model_selection_stops_at_the_minimum_number_of_components() {
        let truth = BoxedGaussian {
            mean: 0.0,
            sigma: 0.6,
            width: 0.5,
        };
        let profiles: Vec<Profile> = (0..3)
            .map(|_| Profile {
                noise: None,
                samples: (0..16)
                    .map(|j| {
                        let s = -4.0 + 0.5 * (j as f64 + 0.5);
                        Sample {
                            s,
                            y: truth.density(s),
                        }
                    })
                    .collect(),
                slit_width: 0.5,
                period: Some(8.0),
                shift_per_depth: 0.0,
            })
            .collect();
        let data = Data::new(&profiles).unwrap();
        let start = State {
            weights: vec![1.0 / 3.0; 3],
            sigmas: vec![0.4, 0.6, 0.9],
            means: Fixed(vec![0.0; 3]),
        };
        for (min, want) in [(1, 1), (2, 2), (3, 3)] {
            let cfg = EmConfig {
                components: 3,
                bic_min_components: min,
                ..EmConfig::default()
            };
            let (state, _, _) = fit(&data, start.clone(), &cfg);
            assert_eq!(state.weights.len(), want, "minimum {min}");
        }
    }

    #[test]
    fn water_fill_respects_floor_and_sums_to_one() {
        let w = water_fill(&[0.5, 0.0, 0.3, 1e-9, 0.2], 0.01);
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!(w.iter().all(|&x| x >= 0.01 - 1e-15));
        assert_eq!(w[1], 0.01);
        assert_eq!(w[3], 0.01);
        // Free weights keep their ratios.
        assert!((w[0] / w[2] - 0.5 / 0.3).abs() < 1e-12);
    }

    #[test]
    fn water_fill_is_the_constrained_maximum() {
        // Compare with random feasible points: none beats it.
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let n = [0.6, 0.001, 0.25, 0.149, 0.0];
        let floor = 0.02;
        let objective = |w: &[f64]| n.iter().zip(w).map(|(a, b)| a * b.ln()).sum::<f64>();
        let best = objective(&water_fill(&n, floor));
        for _ in 0..2000 {
            let raw: Vec<f64> = (0..5).map(|_| rng.r#gen::<f64>()).collect();
            let s: f64 = raw.iter().sum();
            let w: Vec<f64> = raw
                .iter()
                .map(|r| floor + r / s * (1.0 - 5.0 * floor))
                .collect();
            assert!(objective(&w) <= best + 1e-12);
        }
    }
}
