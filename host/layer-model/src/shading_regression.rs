//! Shading regression: the part of the per-projector subsurface amplitudes that depends on the
//! light direction, explained by a first-order error of the surface normal and removed by
//! correcting the normal.
//!
//! Why: each training projector `p` gives its own amplitude estimate of a pixel,
//! `a_p = F_p / (E_p W_p)` (profile flux over modelled irradiance times slit width). The modelled
//! irradiance `E_p ~ n . l_p` uses the estimated normal `n`; a normal error `delta` (tangent to the
//! surface) makes `ln(E_true / E_model) ~ delta . u_p` with `u_p = l_t / (n . l)` (tangential part
//! of the unit direction to the light over its normal part). On the quick head with the estimated
//! calibration (normals 4.7 deg mean error) this light-dependent error is as large as the skin's
//! true amplitude variation, and it does not transfer: averaged over three projectors it predicts
//! the held-out projector's error with the wrong sign (the held-out projector sits opposite the
//! training ones' mean direction). So the per-pixel amplitudes lost to the homogeneous model.
//!
//! Model, per pixel, over the training projectors `p` that light it and the channels `c`:
//!
//! ```text
//!     y_pc = ln a_pc = alpha_c + delta . u_p + noise
//! ```
//!
//! `alpha_c` (the light-independent log amplitude) and `delta` (2-D, in a tangent basis of the
//! pixel) are the posterior mode under the priors `alpha_c ~ N(mu_c, s2 / kappa)` and
//! `delta ~ N(0, s2 / lambda)` (ridge). `lambda` and `kappa` are chosen on a grid by
//! leave-one-projector-out cross-validation on the training projectors alone: fit on all but one
//! projector, predict the left-out projector's `y`, sum the squared errors over pixels. The
//! held-out projector and the truth are never used. The corrected normal is
//! `normalize(n + delta_1 e_1 + delta_2 e_2)` (to first order `ln(n' . l / n . l) = delta . u`).
//!
//! Conventions: light directions from the surface point to the projector centre (world frame,
//! mm); `(e_1, e_2)` is [`tangent_basis`] of the pixel's normal.

use nalgebra::{Matrix2, Vector2, Vector3};
use rayon::prelude::*;
use serde::Serialize;

use super::profiles::{GeometryMap, SlitSweep};
use super::surface::Surface;

/// Errors of the shading regression.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum ShadingError {
    /// The per-projector inputs disagree in number.
    #[error("{geometries} projector geometries, {sweeps} slit sweeps, {centres} projector centres")]
    ProjectorCount {
        geometries: usize,
        sweeps: usize,
        centres: usize,
    },
    /// A per-pixel input does not have the surface's size.
    #[error("{what} has {got} pixels, the surface {want}")]
    SizeMismatch {
        what: &'static str,
        got: usize,
        want: usize,
    },
}

/// One projector's observation of a pixel: its light-direction term and the log amplitude per
/// channel (`None` where that channel's profiles carry no light).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    pub u: Vector2<f64>,
    pub y: [Option<f64>; 3],
}

/// Every pixel's observations, in pixel order, kept in blocks of 4096 pixels: each
/// block one list of observations and where each pixel's part of it ends. Why not a list per
/// pixel: at full size the ~1.4 million lists were allocated, walked (the channel means, the
/// outliers, the solves) and freed one by one. With the blocks (and the normals corrected in
/// place, [`refine_normals`]) the fit stage's `fit_normals` phase went 0.66-0.71 -> 0.50-0.62 s
/// wall and 1.11-1.18 -> 0.88-1.09 CPU-s (full-size `process --until fit`, 6 runs of each build
/// in alternated pairs; the model file byte-identical in every pair).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PixelObservations {
    blocks: Vec<ObservationBlock>,
}

/// Pixels per block of [`PixelObservations`]: ~350 blocks at full size, each list a few hundred
/// kB (reused from the heap, never mapped afresh).
const BLOCK_PIXELS: usize = 4096;

/// The observations of consecutive pixels.
#[derive(Debug, Clone, Default, PartialEq)]
struct ObservationBlock {
    /// Per pixel: the end of its observations in `list` (each starts where the previous ends).
    ends: Vec<u32>,
    list: Vec<Observation>,
}

impl ObservationBlock {
    /// Appends a pixel with `observations`.
    fn push_pixel(&mut self, observations: impl IntoIterator<Item = Observation>) {
        self.list.extend(observations);
        // At most BLOCK_PIXELS pixels of a few observations each.
        self.ends.push(self.list.len() as u32);
    }

    /// The observations of the block's pixel `j` (empty beyond its last pixel).
    fn pixel(&self, j: usize) -> &[Observation] {
        let start = match j.checked_sub(1) {
            Some(before) => self.ends.get(before).copied(),
            None => Some(0),
        };
        match (start, self.ends.get(j)) {
            (Some(start), Some(&end)) => &self.list[start as usize..end as usize],
            _ => &[],
        }
    }

    /// The observations of each pixel, in order.
    fn pixels(&self) -> impl Iterator<Item = &[Observation]> + '_ {
        (0..self.ends.len()).map(|j| self.pixel(j))
    }

    /// Keeps the observations for which `keep` (which may change them) says true, each pixel's
    /// in order.
    fn retain(&mut self, mut keep: impl FnMut(&mut Observation) -> bool) {
        let (mut start, mut kept) = (0, 0);
        for end in &mut self.ends {
            for read in start..*end as usize {
                let mut o = self.list[read];
                if keep(&mut o) {
                    self.list[kept] = o;
                    kept += 1;
                }
            }
            start = *end as usize;
            *end = kept as u32;
        }
        self.list.truncate(kept);
    }
}

impl PixelObservations {
    /// The observations of pixel after pixel, one list each.
    pub fn from_lists(lists: Vec<Vec<Observation>>) -> Self {
        Self::from_fn(lists.len(), |i| lists[i].iter().copied())
    }

    /// The observations `pixel(i)` of pixels `0..n`, the blocks made on every core.
    fn from_fn<I: IntoIterator<Item = Observation>>(
        n: usize,
        pixel: impl Fn(usize) -> I + Sync,
    ) -> Self {
        let blocks = (0..n.div_ceil(BLOCK_PIXELS))
            .into_par_iter()
            .map(|b| {
                let mut block = ObservationBlock::default();
                for i in b * BLOCK_PIXELS..((b + 1) * BLOCK_PIXELS).min(n) {
                    block.push_pixel(pixel(i));
                }
                block
            })
            .collect();
        Self { blocks }
    }

    /// Number of pixels (with or without observations).
    pub fn len(&self) -> usize {
        self.blocks.iter().map(|b| b.ends.len()).sum()
    }

    /// Whether there is no pixel.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The observations of each pixel, in pixel order.
    pub fn pixels(&self) -> impl Iterator<Item = &[Observation]> + '_ {
        self.blocks.iter().flat_map(ObservationBlock::pixels)
    }

    /// The observations of pixel `i` (empty beyond the last pixel).
    fn pixel(&self, i: usize) -> &[Observation] {
        self.blocks
            .get(i / BLOCK_PIXELS)
            .map_or(&[], |block| block.pixel(i % BLOCK_PIXELS))
    }

    /// `solve` of each pixel's observations, in pixel order, on every core. Indexed, so the
    /// results are written in place: a list collected from the blocks was gathered from
    /// pieces, and one made first and filled was faulted in on one thread (either way the
    /// solves took twice as long at full size).
    fn solve_each<T: Send>(
        &self,
        solve: impl Fn(&[Observation]) -> Option<T> + Sync,
    ) -> Vec<Option<T>> {
        (0..self.len())
            .into_par_iter()
            .map(|i| solve(self.pixel(i)))
            .collect()
    }
}

/// The fitted parameters of one pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelShading {
    /// Light-independent log amplitude per channel.
    pub alpha: [f64; 3],
    /// Tangential normal correction in the pixel's tangent basis.
    pub delta: Vector2<f64>,
}

/// Ridge strengths tried by the cross-validation; the largest is "no correction".
const LAMBDAS: [f64; 9] = [0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 1e9];
/// Amplitude prior strengths tried (0: each pixel's own amplitude).
const KAPPAS: [f64; 6] = [0.0, 0.1, 0.3, 1.0, 3.0, 10.0];
/// Observations whose log amplitude is further than this from the channel's mean are left out
/// (shadow edges, grazing light: factors beyond e^1.5 ~ 4.5 are not skin).
const OUTLIER_LOG: f64 = 1.5;
/// Largest tangential correction kept (about 27 degrees).
const MAX_DELTA: f64 = 0.5;
/// At most this many pixels score the cross-validation (evenly spaced).
const CV_PIXELS: usize = 20_000;

/// Regression strengths and what the cross-validation saw.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ShadingReport {
    /// Chosen ridge on the normal correction (`1e9`: no correction).
    pub lambda: f64,
    /// Chosen amplitude prior strength.
    pub kappa: f64,
    /// Mean squared leave-one-projector-out error of `y` (per observation) at the choice, with no
    /// correction and no amplitude prior (`lambda = 1e9, kappa = 0`, the per-pixel mean), and with
    /// the subject mean alone.
    pub cv_mse: f64,
    pub cv_mse_no_correction: f64,
    pub cv_mse_subject_mean: f64,
    /// Pixels scored by the cross-validation and pixels corrected.
    pub cv_pixels: usize,
    pub corrected_pixels: usize,
    /// Mean and 95th percentile of the normal correction (degrees).
    pub mean_correction_deg: f64,
    pub p95_correction_deg: f64,
}

/// An orthonormal basis of the plane perpendicular to `n` (unit).
pub fn tangent_basis(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = n.cross(&helper).normalize();
    (e1, n.cross(&e1))
}

/// `u = l_t / (n . l)` in the basis of [`tangent_basis`]; `None` when the light is behind.
pub fn light_term(
    point: &Vector3<f64>,
    normal: &Vector3<f64>,
    centre: &Vector3<f64>,
) -> Option<Vector2<f64>> {
    let l = (centre - point).try_normalize(1e-12)?;
    let c = l.dot(normal);
    if c <= 1e-3 {
        return None;
    }
    let (e1, e2) = tangent_basis(normal);
    Some(Vector2::new(l.dot(&e1) / c, l.dot(&e2) / c))
}

/// The normal rotated by the tangential correction `delta` (basis of [`tangent_basis`]).
pub fn corrected_normal(normal: &Vector3<f64>, delta: &Vector2<f64>) -> Vector3<f64> {
    let (e1, e2) = tangent_basis(normal);
    (normal + e1 * delta.x + e2 * delta.y).normalize()
}

/// Posterior mode of one pixel from `obs` (leaving out observation `skip`), with channel means
/// `mu`; `None` when no observation is left.
///
/// The normal equations of the five unknowns (three log amplitudes `alpha_c`, the correction
/// `delta`) are solved by eliminating the amplitudes: each channel's row gives
/// `alpha_c = (s_c + k mu_c - U_c . delta) / (n_c + k)` (`n_c` observations of channel `c`
/// with sum `s_c`, their light terms summing to `U_c`), which leaves the 2x2 Schur complement
/// `(S + lambda I - sum_c U_c U_c^T / (n_c + k)) delta = t - sum_c U_c (s_c + k mu_c) / (n_c + k)`
/// with `S = sum u u^T`, `t = sum u y` over every observed channel. Why: the cross-validation
/// solves ~3.9 million of these at full size (54 strengths x 20 000 pixels x 3 left out, then
/// every pixel), and the 5x5 outer products and Cholesky factorisation were a third of the
/// normals' refinement.
fn solve_pixel(
    obs: &[Observation],
    skip: Option<usize>,
    mu: &[f64; 3],
    lambda: f64,
    kappa: f64,
) -> Option<PixelShading> {
    PixelSums::of(obs, skip)?.solve(mu, lambda, kappa)
}

/// The sums [`solve_pixel`]'s normal equations are built from: they do not depend on the
/// strengths, so the cross-validation takes them once per left-out observation for all 54
/// strengths instead of once per strength (the same sums, so the same solutions bit for bit).
#[derive(Debug, Clone, Copy)]
struct PixelSums {
    /// Per channel: observation count, sum of log amplitudes, sum of light terms.
    n: [f64; 3],
    s: [f64; 3],
    u_sum: [Vector2<f64>; 3],
    uu: Matrix2<f64>,
    uy: Vector2<f64>,
}

impl PixelSums {
    /// The sums over `obs` without observation `skip`; `None` when no observation is left.
    fn of(obs: &[Observation], skip: Option<usize>) -> Option<Self> {
        let (mut n, mut s) = ([0.0f64; 3], [0.0f64; 3]);
        let mut u_sum = [Vector2::<f64>::zeros(); 3];
        let mut uu = Matrix2::<f64>::zeros();
        let mut uy = Vector2::<f64>::zeros();
        let mut any = false;
        for (j, o) in obs.iter().enumerate() {
            if Some(j) == skip {
                continue;
            }
            for (c, y) in o.y.iter().enumerate() {
                let Some(y) = *y else { continue };
                any = true;
                n[c] += 1.0;
                s[c] += y;
                u_sum[c] += o.u;
                uu += o.u * o.u.transpose();
                uy += o.u * y;
            }
        }
        any.then_some(Self {
            n,
            s,
            u_sum,
            uu,
            uy,
        })
    }

    /// The posterior mode with strengths `lambda` and `kappa` (see [`solve_pixel`]).
    fn solve(&self, mu: &[f64; 3], lambda: f64, kappa: f64) -> Option<PixelShading> {
        self.with_kappa(mu, kappa).solve(lambda)
    }

    /// What [`PixelSums::solve`] computes before the ridge `lambda` enters, for amplitude
    /// prior strength `kappa` and channel means `mu`.
    fn with_kappa(&self, mu: &[f64; 3], kappa: f64) -> KappaTerms<'_> {
        let Self {
            n, s, u_sum, uy, ..
        } = self;
        // A tiny amplitude prior keeps channels without an observation at the subject mean.
        let k = kappa.max(1e-9);
        let mut r = *uy;
        let mut outer = [Matrix2::<f64>::zeros(); 3];
        for c in 0..3 {
            let inv = 1.0 / (n[c] + k);
            outer[c] = u_sum[c] * u_sum[c].transpose() * inv;
            r -= u_sum[c] * ((s[c] + k * mu[c]) * inv);
        }
        KappaTerms {
            sums: self,
            prior: std::array::from_fn(|c| s[c] + k * mu[c]),
            count: std::array::from_fn(|c| n[c] + k),
            outer,
            r,
        }
    }
}

/// A pixel's normal equations for one amplitude prior strength `kappa`, every term that does
/// not depend on the ridge `lambda` made ([`PixelSums::with_kappa`]). Why: the cross-validation
/// solves each left-out observation for 9 ridges per `kappa`, and the amplitudes' elimination
/// (three divisions and outer products) is the same for all 9. The same operations in the same
/// order as solving afresh, so the same solutions bit for bit.
struct KappaTerms<'a> {
    sums: &'a PixelSums,
    /// Per channel `s_c + k mu_c` and `n_c + k`.
    prior: [f64; 3],
    count: [f64; 3],
    /// Per channel `U_c U_c^T / (n_c + k)`, subtracted from `S + lambda I`.
    outer: [Matrix2<f64>; 3],
    /// The right-hand side `t - sum_c U_c (s_c + k mu_c) / (n_c + k)`.
    r: Vector2<f64>,
}

impl KappaTerms<'_> {
    /// The posterior mode with ridge `lambda`.
    fn solve(&self, lambda: f64) -> Option<PixelShading> {
        let mut m = self.sums.uu + Matrix2::identity() * lambda;
        for outer in &self.outer {
            m -= outer;
        }
        let delta = m.cholesky()?.solve(&self.r);
        let u_sum = &self.sums.u_sum;
        let alpha: [f64; 3] =
            std::array::from_fn(|c| (self.prior[c] - u_sum[c].dot(&delta)) / self.count[c]);
        Some(PixelShading {
            alpha,
            delta: clamped_correction(delta),
        })
    }
}

/// `delta` shortened to [`MAX_DELTA`] when it is longer.
fn clamped_correction(delta: Vector2<f64>) -> Vector2<f64> {
    let norm = delta.norm();
    if norm > MAX_DELTA {
        delta * (MAX_DELTA / norm)
    } else {
        delta
    }
}

/// Squared prediction errors and count of observation `left` (with its pixel's other
/// observations' terms `others` for one `kappa`, `None` when it has none) under ridge `lambda`.
fn left_out_error(left: &Observation, others: Option<&KappaTerms>, lambda: f64) -> (f64, usize) {
    let Some(fit) = others.and_then(|terms| terms.solve(lambda)) else {
        return (0.0, 0);
    };
    let shade = fit.delta.dot(&left.u);
    left.y
        .iter()
        .enumerate()
        .filter_map(|(c, y)| y.map(|y| (y - fit.alpha[c] - shade).powi(2)))
        .fold((0.0, 0), |(s, n), e| (s + e, n + 1))
}

/// Channel means of the observations.
fn channel_means(pixels: &PixelObservations) -> [f64; 3] {
    let mut sum = [0.0; 3];
    let mut count = [0usize; 3];
    for o in pixels.pixels().flatten() {
        for c in 0..3 {
            if let Some(y) = o.y[c] {
                sum[c] += y;
                count[c] += 1;
            }
        }
    }
    std::array::from_fn(|c| {
        if count[c] > 0 {
            sum[c] / count[c] as f64
        } else {
            0.0
        }
    })
}

/// Leave-one-projector-out mean squared error per observation for every `(lambda, kappa)`, over
/// the pixels with at least two observations (at most [`CV_PIXELS`] of them, evenly spaced).
fn cross_validate(pixels: &PixelObservations, mu: &[f64; 3]) -> (Vec<(f64, f64, f64)>, usize) {
    let scorable: Vec<&[Observation]> = pixels.pixels().filter(|o| o.len() >= 2).collect();
    let step = scorable.len().div_ceil(CV_PIXELS).max(1);
    let chosen: Vec<&[Observation]> = scorable.into_iter().step_by(step).collect();
    // Every left-out observation with the sums of the others, in the order they are scored.
    let left_out: Vec<(&Observation, Option<PixelSums>)> = chosen
        .par_iter()
        .flat_map_iter(|obs| {
            obs.iter()
                .enumerate()
                .map(|(left, o)| (o, PixelSums::of(obs, Some(left))))
        })
        .collect();
    // Per kappa, every ridge's sum over the left-out observations in their order (each
    // observation's terms made once for its 9 ridges).
    let per_kappa: Vec<[(f64, usize); LAMBDAS.len()]> = KAPPAS
        .par_iter()
        .map(|&kappa| {
            let mut sums = [(0.0, 0usize); LAMBDAS.len()];
            for (left, others) in &left_out {
                let terms = others.as_ref().map(|o| o.with_kappa(mu, kappa));
                for (acc, &lambda) in sums.iter_mut().zip(&LAMBDAS) {
                    let (s, m) = left_out_error(left, terms.as_ref(), lambda);
                    acc.0 += s;
                    acc.1 += m;
                }
            }
            sums
        })
        .collect();
    // The table ridge by ridge, then strength, as the choice reads it (first minimum wins).
    let table = LAMBDAS
        .iter()
        .enumerate()
        .flat_map(|(l, &lambda)| {
            KAPPAS.iter().zip(&per_kappa).map(move |(&kappa, sums)| {
                let (sum, n) = sums[l];
                (
                    lambda,
                    kappa,
                    if n > 0 { sum / n as f64 } else { f64::INFINITY },
                )
            })
        })
        .collect();
    (table, chosen.len())
}

/// Subject-mean-only error: every observation predicted by its channel mean.
fn subject_mean_error(pixels: &PixelObservations, mu: &[f64; 3]) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for o in pixels.pixels().filter(|o| o.len() >= 2).flatten() {
        for (y, m) in o.y.iter().zip(mu) {
            if let Some(y) = y {
                sum += (y - m).powi(2);
                n += 1;
            }
        }
    }
    if n > 0 { sum / n as f64 } else { f64::INFINITY }
}

/// Drops observations of a channel that are outliers against its mean, then the observations
/// left without a channel (blocks of pixels in parallel).
fn without_outliers(pixels: &mut PixelObservations, mu: &[f64; 3]) {
    pixels.blocks.par_iter_mut().for_each(|block| {
        block.retain(|o| {
            for (y, m) in o.y.iter_mut().zip(mu) {
                if y.is_some_and(|y| (y - m).abs() > OUTLIER_LOG) {
                    *y = None;
                }
            }
            o.y.iter().any(Option::is_some)
        });
    });
}

/// Fits every pixel (`None` without observations) with the strengths chosen by
/// leave-one-projector-out cross-validation. Takes the observations: their outliers are
/// dropped in place (a copy of the ~1.4 million pixels' lists at full size was made serially).
pub fn fit_shading(pixels: PixelObservations) -> (Vec<Option<PixelShading>>, ShadingReport) {
    let mut clean = pixels;
    let mu0 = channel_means(&clean);
    without_outliers(&mut clean, &mu0);
    let mu = channel_means(&clean);
    let (table, cv_pixels) = cross_validate(&clean, &mu);
    let (lambda, kappa, cv_mse) = table
        .iter()
        .copied()
        .min_by(|a, b| a.2.total_cmp(&b.2))
        .unwrap_or((LAMBDAS[LAMBDAS.len() - 1], 0.0, f64::INFINITY));
    let no_correction = table
        .iter()
        .find(|t| t.0 == LAMBDAS[LAMBDAS.len() - 1] && t.1 == 0.0)
        .map_or(f64::INFINITY, |t| t.2);
    let fits = clean.solve_each(|obs| solve_pixel(obs, None, &mu, lambda, kappa));
    let mut angles: Vec<f64> = fits
        .iter()
        .flatten()
        .map(|f| f.delta.norm().atan().to_degrees())
        .collect();
    // `total_cmp` orders every value and equal ones are the same bits: the same list as a
    // serial sort, so the same mean.
    angles.par_sort_unstable_by(f64::total_cmp);
    let report = ShadingReport {
        lambda,
        kappa,
        cv_mse,
        cv_mse_no_correction: no_correction,
        cv_mse_subject_mean: subject_mean_error(&clean, &mu),
        cv_pixels,
        corrected_pixels: angles.len(),
        mean_correction_deg: if angles.is_empty() {
            0.0
        } else {
            angles.iter().sum::<f64>() / angles.len() as f64
        },
        p95_correction_deg: angles
            .get((angles.len() as f64 * 0.95) as usize)
            .or(angles.last())
            .copied()
            .unwrap_or(0.0),
    };
    (fits, report)
}

/// The observations of every surface pixel from the training projectors' slit profiles.
pub fn observations(
    surface: &Surface,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    centres: &[Vector3<f64>],
) -> Result<PixelObservations, ShadingError> {
    if geometries.len() != sweeps.len() || centres.len() != sweeps.len() {
        return Err(ShadingError::ProjectorCount {
            geometries: geometries.len(),
            sweeps: sweeps.len(),
            centres: centres.len(),
        });
    }
    if let Some(g) = geometries.iter().find(|g| g.len() != surface.len()) {
        return Err(ShadingError::SizeMismatch {
            what: "projector geometry",
            got: g.len(),
            want: surface.len(),
        });
    }
    let surface_pixel = |i: usize| {
        geometries
            .iter()
            .zip(sweeps)
            .zip(centres)
            .filter_map(move |((geo, sweep), centre)| {
                let g = *geo.get(i)?;
                let u = light_term(&surface.points[i], &surface.normals[i], centre)?;
                let y: [Option<f64>; 3] =
                    std::array::from_fn(|c| log_amplitude(sweep.fluxes(i, c, &g)));
                y.iter()
                    .any(Option::is_some)
                    .then_some(Observation { u, y })
            })
    };
    Ok(PixelObservations::from_fn(surface.len(), |i| {
        surface.mask[i]
            .then(|| surface_pixel(i))
            .into_iter()
            .flatten()
    }))
}

/// `ln(sum F / sum E W)` of a pixel's `(flux, E W)` per axis ([`SlitSweep::fluxes`]: its
/// profiles' [`crate::mixture::Profile::flux`] and `E` times slit width, without building the profiles'
/// samples, which took a third of the regression's time), summed in axis order as the profiles'
/// were; `None` unless both sums are positive.
fn log_amplitude(per_axis: impl Iterator<Item = (f64, f64)>) -> Option<f64> {
    let mut parts = [(0.0, 0.0); 2];
    let mut count = 0;
    for (slot, part) in parts.iter_mut().zip(per_axis) {
        *slot = part;
        count += 1;
    }
    let parts = &parts[..count];
    let flux: f64 = parts.iter().map(|p| p.0).sum();
    let ew: f64 = parts.iter().map(|p| p.1).sum();
    (flux > 0.0 && ew > 0.0).then(|| (flux / ew).ln())
}

/// Corrects every pixel's normal of `surface`, in place, by the shading regression of its
/// training observations; the report says what the cross-validation chose. In place: a
/// corrected copy (70 MB at full size) was made and the original dropped.
pub fn refine_normals(
    surface: &mut Surface,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    centres: &[Vector3<f64>],
) -> Result<ShadingReport, ShadingError> {
    let pixels = observations(surface, geometries, sweeps, centres)?;
    let (fits, report) = fit_shading(pixels);
    surface
        .normals
        .par_iter_mut()
        .zip(&fits)
        .for_each(|(n, fit)| {
            if let Some(f) = fit {
                *n = corrected_normal(n, &f.delta);
            }
        });
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The 5x5 normal equations of a pixel (three log amplitudes, the normal correction) built
    /// and solved whole, as `solve_pixel` did before it eliminated the amplitudes: the reference
    /// its Schur complement is checked against.
    fn solve_pixel_whole(
        obs: &[Observation],
        skip: Option<usize>,
        mu: &[f64; 3],
        lambda: f64,
        kappa: f64,
    ) -> Option<PixelShading> {
        use nalgebra::{Matrix5, Vector5};
        let (mut a, mut b) = (Matrix5::<f64>::zeros(), Vector5::<f64>::zeros());
        let mut any = false;
        let kept = obs.iter().enumerate().filter(|(j, _)| Some(*j) != skip);
        for (_, o) in kept {
            for (c, y) in o.y.iter().enumerate() {
                let Some(y) = *y else { continue };
                any = true;
                let mut row = Vector5::new(0.0, 0.0, 0.0, o.u.x, o.u.y);
                row[c] = 1.0;
                a += row * row.transpose();
                b += row * y;
            }
        }
        if !any {
            return None;
        }
        let k = kappa.max(1e-9);
        for c in 0..3 {
            a[(c, c)] += k;
            b[c] += k * mu[c];
        }
        a[(3, 3)] += lambda;
        a[(4, 4)] += lambda;
        let x = a.cholesky()?.solve(&b);
        let delta = Vector2::new(x[3], x[4]);
        Some(PixelShading {
            alpha: [x[0], x[1], x[2]],
            delta: clamped_correction(delta),
        })
    }

    /// [`PixelSums::solve`] as it was written before the terms of one `kappa` were shared
    /// between ridges: the reference [`KappaTerms`] is checked against bit for bit.
    fn solve_in_one(
        sums: &PixelSums,
        mu: &[f64; 3],
        lambda: f64,
        kappa: f64,
    ) -> Option<PixelShading> {
        let PixelSums {
            n,
            s,
            u_sum,
            uu,
            uy,
        } = sums;
        let k = kappa.max(1e-9);
        let mut m = uu + Matrix2::identity() * lambda;
        let mut r = *uy;
        for c in 0..3 {
            let inv = 1.0 / (n[c] + k);
            m -= u_sum[c] * u_sum[c].transpose() * inv;
            r -= u_sum[c] * ((s[c] + k * mu[c]) * inv);
        }
        let delta = m.cholesky()?.solve(&r);
        let alpha: [f64; 3] =
            std::array::from_fn(|c| (s[c] + k * mu[c] - u_sum[c].dot(&delta)) / (n[c] + k));
        Some(PixelShading {
            alpha,
            delta: clamped_correction(delta),
        })
    }

    /// A pixel of 1 to `most` random observations (each channel missing one time in five) and,
    /// half the time, one of them to leave out.
    fn random_pixel(rng: &mut rand_pcg::Pcg64, most: usize) -> (Vec<Observation>, Option<usize>) {
        let count = rng.gen_range(1..=most);
        let obs: Vec<Observation> = (0..count)
            .map(|_| Observation {
                u: Vector2::new(rng.gen_range(-1.5..1.5), rng.gen_range(-1.5..1.5)),
                y: std::array::from_fn(|_| rng.gen_bool(0.8).then(|| rng.gen_range(-3.0..1.0))),
            })
            .collect();
        let skip = rng.gen_bool(0.5).then(|| rng.gen_range(0..count));
        (obs, skip)
    }

    /// One `kappa`'s terms solved for every ridge give what solving each strength in one go
    /// gives, bit for bit, on random pixels: channels missing, an observation left out, every
    /// strength of the cross-validation's grid.
    #[test]
    fn kappa_terms_solve_every_ridge_as_solving_in_one_go() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(41);
        let mut compared = 0;
        for _ in 0..3000 {
            let (obs, skip) = random_pixel(&mut rng, 5);
            let mu = [-1.0, -1.3, -1.8];
            let Some(sums) = PixelSums::of(&obs, skip) else {
                continue;
            };
            for &kappa in &KAPPAS {
                let terms = sums.with_kappa(&mu, kappa);
                for &lambda in &LAMBDAS {
                    let bits = |f: Option<PixelShading>| {
                        f.map(|f| (f.alpha.map(f64::to_bits), f.delta.map(f64::to_bits)))
                    };
                    let want = solve_in_one(&sums, &mu, lambda, kappa);
                    compared += usize::from(want.is_some());
                    assert_eq!(bits(terms.solve(lambda)), bits(want), "{lambda} {kappa}");
                }
            }
        }
        assert!(compared > 50_000, "only {compared} solutions compared");
    }

    /// Eliminating the amplitudes gives the whole system's solution (to rounding) on random
    /// pixels: channels missing from some observations or from all, an observation left out,
    /// strengths from nearly none to strong, corrections past the clamp.
    #[test]
    fn schur_complement_solve_equals_the_whole_normal_equations() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(17);
        let mut compared = 0;
        for _ in 0..2000 {
            let (obs, skip) = random_pixel(&mut rng, 6);
            let mu = [-1.0, -1.3, -1.8];
            let lambda = 10f64.powf(rng.gen_range(-3.0..2.0));
            let kappa = 10f64.powf(rng.gen_range(-4.0..2.0));
            let fast = solve_pixel(&obs, skip, &mu, lambda, kappa);
            let whole = solve_pixel_whole(&obs, skip, &mu, lambda, kappa);
            match (fast, whole) {
                (Some(f), Some(w)) => {
                    compared += 1;
                    let scale = 1.0 + w.alpha.iter().map(|a| a.abs()).fold(0.0, f64::max);
                    for c in 0..3 {
                        assert!(
                            (f.alpha[c] - w.alpha[c]).abs() < 1e-9 * scale,
                            "{f:?} {w:?}"
                        );
                    }
                    assert!((f.delta - w.delta).norm() < 1e-9, "{f:?} {w:?}");
                }
                (None, None) => {}
                (f, w) => panic!("one solved, the other did not: {f:?} {w:?}"),
            }
        }
        assert!(compared > 1500, "{compared}");
    }

    /// The blocks hold what the per-pixel lists held, in order, across block boundaries and
    /// with pixels without observations: read in order and by index, filtered as the lists are
    /// by `retain`, solved pixel by pixel in order.
    #[test]
    fn blocks_keep_every_pixels_observations_in_order() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let pixels = 2 * BLOCK_PIXELS + 37;
        let mut lists: Vec<Vec<Observation>> = (0..pixels)
            .map(|_| {
                if rng.gen_bool(0.3) {
                    Vec::new()
                } else {
                    random_pixel(&mut rng, 4).0
                }
            })
            .collect();
        let mut blocks = PixelObservations::from_lists(lists.clone());
        assert_eq!(blocks.len(), pixels);
        let read: Vec<Vec<Observation>> = blocks.pixels().map(<[Observation]>::to_vec).collect();
        assert_eq!(read, lists);
        for i in (0..pixels)
            .step_by(97)
            .chain([BLOCK_PIXELS - 1, BLOCK_PIXELS, pixels - 1])
        {
            assert_eq!(blocks.pixel(i), lists[i].as_slice(), "pixel {i}");
        }
        assert!(blocks.pixel(pixels).is_empty());
        // Drop one channel of some observations and the observations left without one.
        let keep = |o: &mut Observation| {
            if o.u.x > 0.5 {
                o.y[0] = None;
            }
            o.y.iter().any(Option::is_some) && o.u.y < 1.0
        };
        blocks.blocks.iter_mut().for_each(|b| b.retain(keep));
        for obs in &mut lists {
            obs.retain_mut(keep);
        }
        let read: Vec<Vec<Observation>> = blocks.pixels().map(<[Observation]>::to_vec).collect();
        assert_eq!(read, lists);
        let counts = blocks.solve_each(|obs| (!obs.is_empty()).then_some(obs.len()));
        let want: Vec<Option<usize>> = lists
            .iter()
            .map(|obs| (!obs.is_empty()).then_some(obs.len()))
            .collect();
        assert_eq!(counts, want);
    }

    /// Four lights at the corners of the booth, as seen from a surface point at the origin with
    /// normal `n`.
    fn lights() -> Vec<Vector3<f64>> {
        vec![
            Vector3::new(-260.0, -200.0, 420.0),
            Vector3::new(260.0, -200.0, 420.0),
            Vector3::new(-260.0, 200.0, 420.0),
            Vector3::new(260.0, 200.0, 420.0),
        ]
    }

    /// Synthetic pixels: true normals tilted from the estimated `+z` by a random error of about
    /// `error_deg`, true log amplitudes spread by `spread`, observations `ln(a E_true / E_model)`
    /// plus noise `noise` for the first three lights. Returns the observations, the true tangent
    /// corrections, and the fourth (held-out) light's true log error `ln(a E_true/E_model)`.
    #[allow(clippy::type_complexity)]
    fn synthetic(
        pixels: usize,
        error_deg: f64,
        spread: f64,
        noise: f64,
        seed: u64,
    ) -> (Vec<Vec<Observation>>, Vec<Vector2<f64>>, Vec<[f64; 3]>) {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let n_model = Vector3::z();
        let p = Vector3::zeros();
        let mut obs = Vec::new();
        let mut truth = Vec::new();
        let mut held = Vec::new();
        let tan = error_deg.to_radians().tan();
        for _ in 0..pixels {
            let d = Vector2::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0)) * tan;
            let n_true = corrected_normal(&n_model, &d);
            let alpha: [f64; 3] =
                std::array::from_fn(|c| -1.0 - 0.3 * c as f64 + spread * rng.gen_range(-1.0..1.0));
            let mut o = Vec::new();
            let mut last = [0.0; 3];
            for (k, centre) in lights().iter().enumerate() {
                let l = (centre - p).normalize();
                let shade = (l.dot(&n_true) / l.dot(&n_model)).ln();
                let y: [f64; 3] =
                    std::array::from_fn(|c| alpha[c] + shade + noise * rng.gen_range(-1.0..1.0));
                if k < 3 {
                    o.push(Observation {
                        u: light_term(&p, &n_model, centre).unwrap(),
                        y: y.map(Some),
                    });
                } else {
                    last = y;
                }
            }
            obs.push(o);
            truth.push(d);
            held.push(last);
        }
        (obs, truth, held)
    }

    /// The cross-validation's table equals scoring every strength afresh, each left-out
    /// observation solved from the pixel's other observations (as it was written before the
    /// sums were shared between strengths), bit for bit: pixels with 1 to 3 observations and
    /// channels missing, more pixels than it scores.
    #[test]
    fn cross_validation_equals_solving_every_strength_afresh() {
        let (mut pixels, _, _) = synthetic(CV_PIXELS + 3000, 3.0, 0.3, 0.05, 23);
        for (i, obs) in pixels.iter_mut().enumerate() {
            obs.truncate(1 + i % 3);
            if i % 5 == 0 {
                obs[0].y[i % 3] = None;
            }
        }
        let blocks = PixelObservations::from_lists(pixels.clone());
        let mu = channel_means(&blocks);
        let (table, scored) = cross_validate(&blocks, &mu);
        let scorable: Vec<&Vec<Observation>> = pixels.iter().filter(|o| o.len() >= 2).collect();
        let step = scorable.len().div_ceil(CV_PIXELS).max(1);
        let chosen: Vec<&Vec<Observation>> = scorable.into_iter().step_by(step).collect();
        assert_eq!(scored, chosen.len());
        assert_eq!(table.len(), LAMBDAS.len() * KAPPAS.len());
        for &(lambda, kappa, mse) in &table {
            let (mut sum, mut n) = (0.0, 0usize);
            for obs in &chosen {
                for (left, o) in obs.iter().enumerate() {
                    let Some(fit) = solve_pixel(obs, Some(left), &mu, lambda, kappa) else {
                        continue;
                    };
                    let shade = fit.delta.dot(&o.u);
                    // The observation's channels summed first, then added to the total.
                    let mut own = 0.0;
                    for (c, y) in o.y.iter().enumerate() {
                        if let Some(y) = y {
                            own += (y - fit.alpha[c] - shade).powi(2);
                            n += 1;
                        }
                    }
                    sum += own;
                }
            }
            assert!(n > 0);
            assert_eq!(
                mse.to_bits(),
                (sum / n as f64).to_bits(),
                "{lambda} {kappa}"
            );
        }
    }

    /// The observations as they were made before [`log_amplitude`]: from each axis' whole
    /// profile.
    fn observations_from_profiles(
        surface: &Surface,
        geometries: &[GeometryMap],
        sweeps: &[SlitSweep],
        centres: &[Vector3<f64>],
    ) -> Vec<Vec<Observation>> {
        use crate::mixture::Profile;
        (0..surface.len())
            .map(|i| {
                if !surface.mask[i] {
                    return Vec::new();
                }
                geometries
                    .iter()
                    .zip(sweeps)
                    .zip(centres)
                    .filter_map(|((geo, sweep), centre)| {
                        let g = *geo.get(i)?;
                        let u = light_term(&surface.points[i], &surface.normals[i], centre)?;
                        let y: [Option<f64>; 3] = std::array::from_fn(|c| {
                            let profiles: Vec<Profile> =
                                (0..2).filter_map(|a| sweep.profile(i, c, a, &g)).collect();
                            let flux: f64 = profiles.iter().map(Profile::flux).sum();
                            let ew: f64 =
                                profiles.iter().map(|p| g.irradiance * p.slit_width).sum();
                            (flux > 0.0 && ew > 0.0).then(|| (flux / ew).ln())
                        });
                        y.iter()
                            .any(Option::is_some)
                            .then_some(Observation { u, y })
                    })
                    .collect()
            })
            .collect()
    }

    /// The observations from the sweeps' fluxes are those of the whole profiles, bit for bit:
    /// x and y slits, an x-only projector, dark and negative readings, unlit and masked pixels.
    #[test]
    fn observations_from_fluxes_equal_those_from_the_profiles() {
        use crate::profiles::{AxisGeometry, PixelGeometry, SlitFrame};
        use mlsss_core::capture::{Axis, Pattern};
        let (w, h) = (9, 7);
        let n = w * h;
        let surface = Surface {
            width: w,
            height: h,
            points: (0..n)
                .map(|i| Vector3::new((i % w) as f64 * 0.4, (i / w) as f64 * 0.4, 1.0))
                .collect(),
            normals: (0..n)
                .map(|i| Vector3::new(0.05 * (i % 3) as f64, -0.02, 1.0).normalize())
                .collect(),
            mask: (0..n).map(|i| i % 11 != 4).collect(),
            camera_centre: Vector3::new(0.0, 0.0, 500.0),
        };
        let images: Vec<Vec<[f32; 3]>> = (0..20)
            .map(|j| {
                (0..n)
                    .map(|i| {
                        let v = ((i * 37 + j * 11) % 29) as f32 * 0.01 - 0.04;
                        [v, v * 1.3, if i % 5 == 0 { -0.2 } else { v * 0.6 }]
                    })
                    .collect()
            })
            .collect();
        let frames = |both_axes: bool| -> Vec<SlitFrame> {
            images
                .iter()
                .enumerate()
                .filter(|(j, _)| both_axes || j % 2 == 0)
                .map(|(j, global)| SlitFrame {
                    pattern: Pattern::Slit {
                        axis: if j % 2 == 0 { Axis::X } else { Axis::Y },
                        width: 3,
                        period: 30,
                        offset: 3 * (j / 2) as u32,
                    },
                    global,
                })
                .collect()
        };
        let (both, x_only) = (frames(true), frames(false));
        let sweeps = vec![
            SlitSweep::new(&both, n).unwrap(),
            SlitSweep::new(&x_only, n).unwrap(),
        ];
        let geometry = |k: usize| {
            GeometryMap::from_fn(n, |i| {
                (i % 7 != k + 1).then(|| PixelGeometry {
                    coords: (i as f64 * 1.7 + 0.3, i as f64 * 0.9),
                    irradiance: 0.5 + 0.01 * i as f64,
                    axes: [
                        AxisGeometry {
                            px_per_mm: 1.9,
                            shift_per_depth: 0.2,
                        },
                        AxisGeometry {
                            px_per_mm: 2.3,
                            shift_per_depth: 0.1,
                        },
                    ],
                    shift: Vector3::zeros(),
                })
            })
        };
        let geometries = vec![geometry(0), geometry(1)];
        let centres = vec![
            Vector3::new(-260.0, -200.0, 420.0),
            Vector3::new(260.0, 200.0, 420.0),
        ];
        let fast: Vec<Vec<Observation>> = observations(&surface, &geometries, &sweeps, &centres)
            .unwrap()
            .pixels()
            .map(<[Observation]>::to_vec)
            .collect();
        let plain = observations_from_profiles(&surface, &geometries, &sweeps, &centres);
        type ObservationBits = (u64, u64, [Option<u64>; 3]);
        let bits = |pixels: &[Vec<Observation>]| -> Vec<Vec<ObservationBits>> {
            pixels
                .iter()
                .map(|obs| {
                    obs.iter()
                        .map(|o| {
                            (
                                o.u.x.to_bits(),
                                o.u.y.to_bits(),
                                o.y.map(|y| y.map(f64::to_bits)),
                            )
                        })
                        .collect()
                })
                .collect()
        };
        assert_eq!(bits(&fast), bits(&plain));
        let counted: usize = fast.iter().map(Vec::len).sum();
        assert!(
            counted > n,
            "both projectors observe most pixels: {counted}"
        );
        assert!(
            fast.iter()
                .flatten()
                .any(|o| o.y.iter().any(Option::is_none)),
            "some channel has no positive flux"
        );
    }

    #[test]
    fn a_normal_error_is_recovered_and_predicts_a_new_light() {
        // 6 degree normal errors, small noise: the correction must recover the tilt.
        let (obs, truth, held) = synthetic(3000, 6.0, 0.2, 0.01, 3);
        let (fits, report) = fit_shading(PixelObservations::from_lists(obs.clone()));
        assert!(report.lambda < 1.0, "{report:?}");
        let mut err2 = 0.0;
        let mut size2 = 0.0;
        for (f, d) in fits.iter().zip(&truth) {
            let f = f.unwrap();
            // First order, shrunk by the ridge: the fitted delta matches the tilt's tangent.
            err2 += (f.delta - d).norm_squared();
            size2 += d.norm_squared();
        }
        let rel = (err2 / size2).sqrt();
        assert!(rel < 0.25, "relative error of the correction {rel}");
        // The fourth light, never seen: predicted from alpha + delta . u far better than by the
        // mean of the three seen lights (which carries the opposite shading error).
        let u4 = light_term(&Vector3::zeros(), &Vector3::z(), &lights()[3]).unwrap();
        let (mut e_fit, mut e_mean) = (0.0, 0.0);
        for ((f, o), y4) in fits.iter().zip(&obs).zip(&held) {
            let f = f.unwrap();
            for (c, y4) in y4.iter().enumerate() {
                let mean = o.iter().map(|o| o.y[c].unwrap()).sum::<f64>() / 3.0;
                e_fit += (y4 - f.alpha[c] - f.delta.dot(&u4)).powi(2);
                e_mean += (y4 - mean).powi(2);
            }
        }
        assert!(e_fit < 0.2 * e_mean, "fit {e_fit} vs mean {e_mean}");
    }

    #[test]
    fn pure_noise_is_not_turned_into_a_normal_correction() {
        // Correct normals, noisy amplitudes: the cross-validation must not correct much.
        let (obs, _, _) = synthetic(3000, 0.0, 0.2, 0.1, 5);
        let (fits, report) = fit_shading(PixelObservations::from_lists(obs));
        assert!(report.lambda >= 1.0, "{report:?}");
        let mean_deg = report.mean_correction_deg;
        assert!(mean_deg < 1.5, "mean correction {mean_deg} deg");
        assert_eq!(fits.iter().flatten().count(), 3000);
        // Without signal in the amplitudes beyond the noise, the amplitude prior pulls in.
        assert!(report.cv_mse <= report.cv_mse_no_correction + 1e-12);
    }

    #[test]
    fn corrected_normal_changes_the_cosine_to_first_order() {
        let n = Vector3::new(0.1, -0.2, 1.0).normalize();
        let p = Vector3::new(5.0, 3.0, 0.0);
        let centre = Vector3::new(-200.0, 150.0, 400.0);
        let u = light_term(&p, &n, &centre).unwrap();
        let d = Vector2::new(0.01, -0.02);
        let l = (centre - p).normalize();
        let got = (l.dot(&corrected_normal(&n, &d)) / l.dot(&n)).ln();
        assert!((got - d.dot(&u)).abs() < 1e-3, "{got} vs {}", d.dot(&u));
    }
}
