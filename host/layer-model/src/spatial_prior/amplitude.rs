//! The amplitude half of the prior: each training projector's estimate of a pixel's amplitude,
//! their variance components, and the empirical Bayes shrinkage toward the subject mean.

use rayon::prelude::*;

use crate::profiles::{GeometryMap, SlitSweep};
use crate::render::LayerModel;

/// The amplitudes the prior shrinks, per pixel and channel, and their statistics per channel.
pub(super) struct Amplitudes {
    /// The fit's own amplitude (the sum of the pixel's layer weights).
    pub(super) own: Vec<[f64; 3]>,
    /// Each training projector's estimate ([`projector_amplitudes`]; empty where `own` is 0).
    pub(super) per_projector: PerProjector,
    /// R, G, B.
    pub(super) stats: Vec<AmplitudeStats>,
}

impl Amplitudes {
    /// The amplitudes of the `pixels` pixels of `model`, and their statistics.
    pub(super) fn measure(
        model: &LayerModel,
        pixels: usize,
        geometries: &[GeometryMap],
        sweeps: &[SlitSweep],
    ) -> Self {
        let own: Vec<[f64; 3]> = (0..pixels)
            .into_par_iter()
            .map(|i| {
                std::array::from_fn(|c| {
                    model.layers(i, c).iter().map(|l| f64::from(l.weight)).sum()
                })
            })
            .collect();
        let per_projector = PerProjector::new(pixels, |i, c, values| {
            if own[i][c] > 0.0 {
                projector_amplitudes(i, c, geometries, sweeps, values);
            }
        });
        let stats = channel_stats(&own, &per_projector);
        Self {
            own,
            per_projector,
            stats,
        }
    }
}

/// Per pixel and channel, a list of estimates, stored as one buffer with row offsets. Why: a
/// vector per pixel and channel was ~4 million small allocations at full size (~200 MB held
/// while the prior and the dipole baseline build their models, the stage's peak).
pub(super) struct PerProjector {
    /// `offsets[i * 3 + c]..offsets[i * 3 + c + 1]` indexes `values` for pixel `i`, channel `c`.
    offsets: Vec<u32>,
    values: Vec<f64>,
}

impl PerProjector {
    /// The lists of pixels `0..pixels` that `f(i, c, values)` appends to `values`, runs of
    /// pixels made in parallel and joined in pixel order. Appended, not returned: a vector per
    /// pixel and channel was ~4 million allocations at full size.
    fn new(pixels: usize, f: impl Fn(usize, usize, &mut Vec<f64>) + Sync) -> Self {
        const RUN: usize = 4096;
        let runs: Vec<(Vec<u32>, Vec<f64>)> = (0..pixels.div_ceil(RUN))
            .into_par_iter()
            .map(|r| {
                let (mut ends, mut values) = (Vec::new(), Vec::new());
                for i in r * RUN..((r + 1) * RUN).min(pixels) {
                    for c in 0..3 {
                        f(i, c, &mut values);
                        ends.push(values.len() as u32);
                    }
                }
                (ends, values)
            })
            .collect();
        let mut offsets = Vec::with_capacity(pixels * 3 + 1);
        offsets.push(0u32);
        let mut values = Vec::with_capacity(runs.iter().map(|r| r.1.len()).sum());
        for (ends, run) in runs {
            let base = values.len() as u32;
            offsets.extend(ends.iter().map(|e| base + e));
            values.extend(run);
        }
        Self { offsets, values }
    }

    /// The estimates of pixel `i` in channel `c`.
    pub(super) fn get(&self, i: usize, c: usize) -> &[f64] {
        let k = i * 3 + c;
        &self.values[self.offsets[k] as usize..self.offsets[k + 1] as usize]
    }
}

/// Per channel, the subject mean of the fitted amplitudes, the variance components of the
/// per-projector estimates and the cross-validated prior strength. Channels in parallel; each
/// reads its column of the per-projector lists in place.
fn channel_stats(own: &[[f64; 3]], per_projector: &PerProjector) -> Vec<AmplitudeStats> {
    (0..3)
        .into_par_iter()
        .map(|c| {
            let with: Vec<f64> = own.iter().map(|a| a[c]).filter(|a| *a > 0.0).collect();
            let mean = if with.is_empty() {
                0.0
            } else {
                with.iter().sum::<f64>() / with.len() as f64
            };
            let lists: Vec<&[f64]> = (0..own.len()).map(|i| per_projector.get(i, c)).collect();
            let mut st = amplitude_stats(&lists, mean);
            if let Some((kappa, mse)) = loo_kappa(&lists, mean) {
                st.kappa = Some(kappa);
                st.cv_mse = Some(mse);
            }
            st
        })
        .collect()
}

/// Appends to `out` pixel `i`'s amplitude in channel `c` as each training projector that lights
/// it measures it (its profiles' flux over their `E W`): the same numbers as
/// [`profiles_by_projector`](super::cross_validation)'s groups give, without building the
/// profiles.
fn projector_amplitudes(
    i: usize,
    c: usize,
    geometries: &[GeometryMap],
    sweeps: &[SlitSweep],
    out: &mut Vec<f64>,
) {
    out.extend(geometries.iter().zip(sweeps).filter_map(|(geo, sweep)| {
        let g = *geo.get(i)?;
        let (mut flux, mut ew, mut any) = (0.0, 0.0, false);
        for (f, e) in sweep.fluxes(i, c, &g) {
            flux += f;
            ew += e;
            any = true;
        }
        (any && ew > 0.0).then(|| flux / ew)
    }));
}

/// Variance components of the per-projector amplitude estimates of one channel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct AmplitudeStats {
    pub(super) mean: f64,
    /// Relative noise variance of one projector's estimate.
    pub(super) noise: f64,
    /// Relative variance of the true amplitudes.
    pub(super) signal: f64,
    /// Prior strength chosen by leave-one-projector-out prediction (see [`loo_kappa`]), and its
    /// mean squared error per left-out estimate.
    pub(super) kappa: Option<f64>,
    pub(super) cv_mse: Option<f64>,
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
pub(super) fn loo_kappa<E: AsRef<[f64]>>(per_pixel: &[E], mean: f64) -> Option<(f64, f64)> {
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
    pub(super) fn keep(&self, n: usize) -> f64 {
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
pub(super) fn amplitude_stats<E: AsRef<[f64]>>(per_pixel: &[E], mean: f64) -> AmplitudeStats {
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
