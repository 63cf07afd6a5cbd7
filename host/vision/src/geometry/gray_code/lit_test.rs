//! Step 1 of the algorithm: is a pixel lit by the projector, judged against its own noise.
//!
//! A pixel the projector does not light shows, in every pattern/inverse pair, a difference that
//! is camera noise only: `d_j / sigma_j` is standard normal, where `sigma_j` follows the sensor
//! model at the pair's own level (shot noise from the summed signal plus twice the read noise).
//! The sum `S = sum_j (d_j / sigma_j)^2` over every pair of both axes (and `white - black` when a
//! black frame exists) is then chi-square distributed with one degree of freedom per term. A lit
//! pixel adds its modulation to every term, so `S` is far larger; the test is a chi-square test
//! at a chosen false-alarm probability, not a threshold on absolute levels. This finds a pixel
//! lit at a few noise standard deviations, on dark skin or at grazing light, where a fixed
//! amplitude threshold calls it unlit.
//!
//! Pixels between the `dim` and the `lit` quantiles are reported as dim (flagged): the projector
//! probably lights them, too weakly to decode.

use rayon::prelude::*;

#[cfg(test)]
use super::BitPair;
use super::DecodeParams;

/// How the projector's light shows at a pixel.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) enum Lighting {
    /// No significant modulation: the projector does not light the pixel.
    #[default]
    Unlit,
    /// Significant at the dim false-alarm level only: probably lit, too weakly to decode.
    Dim,
    /// Clearly lit.
    Lit,
}

/// Pixels per block of the blocked loops: the block's sums stay in the L1 cache while every
/// frame is streamed through them in turn.
pub(super) const BLOCK: usize = 2048;

/// The lighting of every pixel from the code pairs of both axes (and white/black if present).
/// The decoder computes it in [`super::bits::first_pass`], with the bits, in one read of the
/// frames; this is the reference of the tests.
#[cfg(test)]
pub(super) fn classify_lighting(
    pairs: &[&BitPair],
    white_black: Option<(&[f32], &[f32])>,
    params: &DecodeParams,
) -> Vec<Lighting> {
    let terms = pairs.len() + usize::from(white_black.is_some());
    let levels = LitLevels::new(terms, params);
    let n = pairs
        .first()
        .map(|p| p.pattern.len())
        .or(white_black.map(|(w, _)| w.len()))
        .unwrap_or(0);
    let mut lighting = vec![Lighting::Unlit; n];
    lighting
        .par_chunks_mut(BLOCK)
        .enumerate()
        .for_each(|(block, out)| {
            let range = block * BLOCK..block * BLOCK + out.len();
            // Frame after frame over the block, in the same order per pixel as a per-pixel sum.
            let mut sum = [0.0f64; BLOCK];
            let sum = &mut sum[..out.len()];
            for p in pairs {
                add_chi_square(sum, &p.pattern, &p.inverse, range.clone(), params);
            }
            if let Some((white, black)) = white_black {
                add_chi_square(sum, white, black, range, params);
            }
            for (l, &s) in out.iter_mut().zip(sum.iter()) {
                *l = levels.classify(s);
            }
        });
    lighting
}

/// Adds `pair_chi_square(a[i], b[i])` for `i` in `range` to `sum[i - range.start]`.
/// The chi-square levels of the lit and dim calls for `terms` pair differences.
#[derive(Debug, Clone, Copy)]
pub(super) struct LitLevels {
    lit: f64,
    dim: f64,
}

impl LitLevels {
    pub(super) fn new(terms: usize, params: &DecodeParams) -> Self {
        Self {
            lit: chi_square_quantile(terms, params.lit_false_alarm as f64),
            dim: chi_square_quantile(terms, params.dim_false_alarm as f64),
        }
    }

    /// The lighting of a pixel whose chi-square sum is `s`.
    pub(super) fn classify(&self, s: f64) -> Lighting {
        if s >= self.lit {
            Lighting::Lit
        } else if s >= self.dim {
            Lighting::Dim
        } else {
            Lighting::Unlit
        }
    }
}

#[cfg(test)]
fn add_chi_square(
    sum: &mut [f64],
    a: &[f32],
    b: &[f32],
    range: std::ops::Range<usize>,
    params: &DecodeParams,
) {
    let (a, b) = (
        a.get(range.clone()).unwrap_or_default(),
        b.get(range).unwrap_or_default(),
    );
    for ((s, &a), &b) in sum.iter_mut().zip(a).zip(b) {
        *s += pair_chi_square(a, b, params);
    }
}

/// Lit pixels much dimmer than the brightest lit pixel around them (within `radius`) become dim:
/// a pixel the projector lights only in part (silhouette, shadow edge) or only through the skin
/// (subsurface light bleeding into a shadow) has the modulation of its lit neighbours' codes, not
/// of its own. Pixels at grazing light are dim together with their neighbours and stay lit.
/// `ratio` 0 turns the check off.
pub(super) fn demote_partly_lit(
    lighting: &mut [Lighting],
    amplitude: &[f32],
    width: usize,
    radius: usize,
    ratio: f32,
) {
    if ratio <= 0.0 || width == 0 {
        return;
    }
    let height = lighting.len() / width;
    // The brightest lit amplitude in the (2 radius + 1)^2 window, clipped at the image's border,
    // as a separable maximum: along each row, then along each column. Unlit pixels count as 0,
    // the floor of the maximum.
    let lit_amplitude: Vec<f32> = amplitude
        .iter()
        .zip(lighting.iter())
        .map(|(&a, &l)| if l == Lighting::Lit { a } else { 0.0 })
        .collect();
    let mut row_max = vec![0.0f32; lit_amplitude.len()];
    row_max
        .par_chunks_mut(width)
        .zip(lit_amplitude.par_chunks(width))
        .for_each(|(out, row)| {
            for (x, o) in out.iter_mut().enumerate() {
                let cols = x.saturating_sub(radius)..(x + radius + 1).min(width);
                *o = row[cols].iter().copied().fold(0.0f32, f32::max);
            }
        });
    lighting
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(y, out)| {
            let rows = y.saturating_sub(radius)..(y + radius + 1).min(height);
            for (x, l) in out.iter_mut().enumerate() {
                if *l != Lighting::Lit {
                    continue;
                }
                let brightest = rows
                    .clone()
                    .map(|ny| row_max[ny * width + x])
                    .fold(0.0f32, f32::max);
                if amplitude[y * width + x] < ratio * brightest {
                    *l = Lighting::Dim;
                }
            }
        });
}

/// `(a - b)^2 / var(a - b)` under the sensor noise model.
pub(super) fn pair_chi_square(a: f32, b: f32, params: &DecodeParams) -> f64 {
    let d = (a - b) as f64;
    d * d / pair_variance(a, b, params)
}

/// Variance of the difference of two frames' values `a` and `b` (shot noise of both plus two
/// read noises).
pub(super) fn pair_variance(a: f32, b: f32, params: &DecodeParams) -> f64 {
    let read = params.read_noise as f64;
    (params.shot_noise_gain as f64 * (a + b).max(0.0) as f64 + 2.0 * read * read)
        .max(f64::MIN_POSITIVE)
}

/// Probability that a chi-square variable with `dof` degrees of freedom exceeds `x`. For even
/// `dof = 2m` it is `exp(-x/2) sum_{i<m} (x/2)^i / i!` (Abramowitz & Stegun 26.4.21); an odd
/// `dof` is rounded up, which makes the test slightly more conservative.
pub(super) fn chi_square_survival(dof: usize, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let m = dof.div_ceil(2).max(1);
    let half = x / 2.0;
    let mut term = 1.0;
    let mut sum = 1.0;
    for i in 1..m {
        term *= half / i as f64;
        sum += term;
    }
    (sum.ln() - half).exp().min(1.0)
}

/// The `x` a chi-square variable with `dof` degrees of freedom exceeds with probability `p`
/// (bisection on [`chi_square_survival`], which falls monotonically).
pub(super) fn chi_square_quantile(dof: usize, p: f64) -> f64 {
    let p = p.clamp(1e-300, 1.0);
    let (mut lo, mut hi) = (0.0f64, 2.0 * dof.max(1) as f64 + 10.0);
    while chi_square_survival(dof, hi) > p {
        hi *= 2.0;
    }
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if chi_square_survival(dof, mid) > p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn survival_matches_published_chi_square_tables() {
        // Abramowitz & Stegun table 26.8: upper 5 % and 0.1 % points.
        assert!((chi_square_quantile(2, 0.05) - 5.991).abs() < 1e-3);
        assert!((chi_square_quantile(16, 0.05) - 26.296).abs() < 1e-3);
        assert!((chi_square_quantile(16, 0.001) - 39.252).abs() < 1e-3);
        // exp(-x/2) exactly for two degrees of freedom.
        assert!((chi_square_survival(2, 7.0) - (-3.5f64).exp()).abs() < 1e-12);
    }

    #[test]
    fn noise_alone_is_unlit_at_the_chosen_false_alarm_rate() {
        use rand::{Rng, SeedableRng};
        let params = DecodeParams {
            dim_false_alarm: 0.01,
            ..DecodeParams::default()
        };
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let n = 20_000;
        let level = 0.01f32;
        let sigma = (params.shot_noise_gain * level + params.read_noise.powi(2)).sqrt();
        let mut frame = || -> Vec<f32> {
            (0..n)
                .map(|_| {
                    // Box-Muller: a standard normal deviate from two uniform ones.
                    let (u1, u2): (f32, f32) = (rng.r#gen::<f32>().max(1e-12), rng.r#gen());
                    let normal = (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos();
                    level + sigma * normal
                })
                .collect()
        };
        let pairs: Vec<BitPair> = (0..16)
            .map(|_| BitPair {
                pattern: frame(),
                inverse: frame(),
            })
            .collect();
        let refs: Vec<&BitPair> = pairs.iter().collect();
        let lighting = classify_lighting(&refs, None, &params);
        let dim = lighting.iter().filter(|&&l| l == Lighting::Dim).count();
        let lit = lighting.iter().filter(|&&l| l == Lighting::Lit).count();
        assert_eq!(lit, 0);
        // 1 % expected: 200 of 20 000, binomial sd 14.
        assert!((140..=260).contains(&dim), "{dim}");
    }

    #[test]
    fn a_pixel_modulated_at_a_few_noise_sigmas_per_pair_is_lit() {
        let params = DecodeParams::default();
        let level = 0.002f32;
        let sigma = pair_variance(level, level, &params).sqrt() as f32;
        // Every pair differs by 2.5 sigma: S = 16 * 6.25 = 100 with 16 terms.
        let pairs: Vec<BitPair> = (0..16)
            .map(|_| BitPair {
                pattern: vec![level + 1.25 * sigma],
                inverse: vec![level - 1.25 * sigma],
            })
            .collect();
        let refs: Vec<&BitPair> = pairs.iter().collect();
        assert_eq!(classify_lighting(&refs, None, &params), vec![Lighting::Lit]);
    }

    #[test]
    fn a_pixel_far_dimmer_than_its_lit_neighbours_is_demoted_to_dim() {
        // A 5x5 patch lit at 0.5, one pixel at 0.1 (lit in part), one dim row at 0.04 whose
        // neighbours are as dim (grazing light: stays lit).
        let width = 5;
        let mut amplitude = vec![0.5f32; 25];
        amplitude[12] = 0.1;
        let mut lighting = vec![Lighting::Lit; 25];
        demote_partly_lit(&mut lighting, &amplitude, width, 2, 0.5);
        assert_eq!(lighting[12], Lighting::Dim);
        assert_eq!(lighting.iter().filter(|&&l| l == Lighting::Dim).count(), 1);
        let dim_patch = vec![0.04f32; 25];
        let mut lighting = vec![Lighting::Lit; 25];
        demote_partly_lit(&mut lighting, &dim_patch, width, 2, 0.5);
        assert!(lighting.iter().all(|&l| l == Lighting::Lit));
    }
}
