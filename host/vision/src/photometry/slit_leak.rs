//! Each pixel's kernel leak at the stripe frequency, measured from the slit sweep (the input of
//! [`super::kernel_leak`]).
//!
//! The slit frames along x light one line of projector columns at a time, stepping by the slit
//! width over the slit period; a camera pixel's values over the sweep sample its response to a
//! line of light against the line's distance: the subsurface kernel along x (blurred by the
//! projector and the slit's width), plus the direct reflection in the slit that lands on it.
//! The leak is that profile's normalised transfer at the stripe frequency `f = 1 / (2 stripe)`.
//! The sweep sees the kernel wrapped into one slit period, whose discrete Fourier coefficients
//! at the sweep's harmonics `j / period` are the kernel's transfer there exactly (a magnitude:
//! independent of where the pixel sits between two slits, and of how far the tail wraps). The
//! leak is read between the two harmonics around `f`:
//!
//! `lambda_j = |Q_j| / (Q_0 sinc(w f_j) exp(-2 pi^2 s^2 f_j^2))`, `ln lambda` linear in `f^2`
//! between them (exact for a Gaussian kernel),
//!
//! with `Q_j` the harmonics of `q`, the slit values less the black-level light (`b` times the
//! white frame), `w` the slit width and `s` the projector blur (the `sinc` undoes the slit's own
//! box, the exponential the blur, which the separation accounts for in the pattern itself).
//!
//! What it cannot see, and how that shows:
//! - The direct reflection sits in the lit slit as if it were kernel, and so does the part of the
//!   kernel narrower than a projector pixel (20-75 % of skin's subsurface light per channel on
//!   the virtual booth): `lambda` is the transfer of reflection and kernel together, and a split
//!   with it keeps almost no direct light. Colour separates them ([`super::dichromatic`]).
//! - Slits as wide as the stripes (the full-size booth: both 3 px) sample the profile no finer
//!   than the stripes themselves: `lambda` then equals the stripes' own contrast and the split
//!   gives almost all light to the global part. Flagged by [`SlitLeakStats::coarse_slits`].
//! - A kernel wider than the slit period wraps around: the profile is flat, `lambda` near 0
//!   (counted in `wide_kernel_pixels`, correct in effect: such a kernel keeps no stripe contrast).
//! - A pixel with no positive slit light (shadow, outside the projector) gets leak 0 and is
//!   counted in `no_profile_pixels`; nothing here returns NaN.

use rayon::prelude::*;

/// Counters of the leak measurement.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct SlitLeakStats {
    pub pixels: u64,
    /// No positive slit light (leak 0).
    pub no_profile_pixels: u64,
    /// The profile is flat over the sweep (kernel wider than the slit period; leak 0).
    pub wide_kernel_pixels: u64,
    /// The slits are not finer than the stripes (see the module documentation).
    pub coarse_slits: bool,
}

/// Geometry of the sweep and the stripes, projector px.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SweepGeometry {
    pub slit_width_px: u32,
    pub stripe_px: u32,
    pub black_level: f32,
    /// Blur of the pattern seen by a camera pixel (defocus and footprint), Gaussian sigma, px.
    pub blur_px: f32,
}

/// How a pixel's leak is read from its slit profile.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LeakReading {
    /// A cosine at the stripe frequency about the brightest slit (the first method): reads a
    /// narrow kernel low by the pixel's offset from that slit and a wide one low by its wrapped
    /// tail, which on dark skin happens to offset the direct reflection the profile holds.
    Cosine,
    /// The sweep's harmonics around the stripe frequency (`HarmonicPlan`): the profile's
    /// transfer read exactly, direct reflection included (see the module documentation), so the
    /// split keeps almost no direct light; the separate stage's default since its version 5,
    /// which reads the direct part by colour instead (`super::dichromatic`).
    #[default]
    Harmonics,
}

/// Leak per pixel and channel from the slit frames of one axis (`slits[j]` the frame of offset
/// `j * slit_width`, row-major RGB) and the white frame `white` (same units).
pub fn leak_from_slits(
    slits: &[&[[f32; 3]]],
    white: &[[f32; 3]],
    geometry: &SweepGeometry,
    reading: LeakReading,
) -> (Vec<[f32; 3]>, SlitLeakStats) {
    let n = white.len();
    let mut stats = SlitLeakStats {
        pixels: n as u64,
        coarse_slits: geometry.slit_width_px >= geometry.stripe_px,
        ..Default::default()
    };
    let reader = match reading {
        LeakReading::Cosine => Reader::Cosine(cosine_weights(slits.len(), geometry)),
        LeakReading::Harmonics => Reader::Harmonics(HarmonicPlan::new(slits.len(), geometry)),
    };
    let measured: Vec<([f32; 3], Outcome)> = (0..n)
        .into_par_iter()
        .map(|i| pixel_leak(slits, white, i, geometry, &reader))
        .collect();
    let mut leaks = Vec::with_capacity(n);
    for (leak, outcome) in measured {
        match outcome {
            Outcome::Ok => {}
            Outcome::NoProfile => stats.no_profile_pixels += 1,
            Outcome::Wide => stats.wide_kernel_pixels += 1,
        }
        leaks.push(leak);
    }
    (leaks, stats)
}

enum Outcome {
    Ok,
    NoProfile,
    Wide,
}

/// A [`LeakReading`] prepared for the sweep.
enum Reader {
    /// `cos(2 pi f x_d) / (sinc(w f) blur(f))` per slit distance from the brightest slit.
    Cosine(Vec<f32>),
    Harmonics(HarmonicPlan),
}

impl Reader {
    /// The leak of one pixel and channel from its slit values less the black floor (`q[d]` for
    /// slit `d`), `None` without light.
    fn leak(&self, q: impl Iterator<Item = f32>, brightest: usize) -> Option<f32> {
        match self {
            Reader::Cosine(weights) => {
                let count = weights.len();
                let (mut total, mut weighted) = (0.0f32, 0.0f32);
                for (j, v) in q.enumerate() {
                    total += v;
                    weighted += v * weights[(j + count - brightest) % count];
                }
                (total > 0.0 && total.is_finite() && weighted.is_finite())
                    .then(|| (weighted / total).clamp(0.0, 1.0))
            }
            Reader::Harmonics(plan) => plan.leak(q),
        }
    }
}

/// `cos(2 pi f x_d) / sinc(w f)` (and the blur) for each wrapped slit distance `d` (index =
/// distance mod the number of slits).
fn cosine_weights(count: usize, geometry: &SweepGeometry) -> Vec<f32> {
    let w = f64::from(geometry.slit_width_px.max(1));
    let f = 1.0 / (2.0 * f64::from(geometry.stripe_px.max(1)));
    let arg = std::f64::consts::PI * w * f;
    let sinc = if arg > 0.0 { arg.sin() / arg } else { 1.0 };
    let blur = f64::from(geometry.blur_px);
    let sinc = sinc * (-2.0 * (std::f64::consts::PI * blur * f).powi(2)).exp();
    (0..count)
        .map(|k| {
            let d = if 2 * k >= count {
                k as f64 - count as f64
            } else {
                k as f64
            };
            ((std::f64::consts::TAU * f * d * w).cos() / sinc) as f32
        })
        .collect()
}

/// The two harmonics of the sweep that bracket the stripe frequency, and how to read the leak
/// between them.
///
/// Why harmonics of the sweep rather than a cosine at the stripe frequency: the sweep samples the
/// kernel wrapped into one slit period, whose discrete Fourier coefficients at the sweep's own
/// frequencies `j / period` are exactly the kernel's transfer there, whatever the pixel's
/// sub-slit position (a magnitude, so no phase to guess) and however far the kernel's tail wraps.
/// A cosine at the stripe frequency, which is no harmonic of the period, is neither: it read
/// narrow kernels low by the pixel's offset from the brightest slit and wide ones low by the
/// wrapped tail. Between the two harmonics `ln lambda` is interpolated linearly in `f^2`, which
/// is exact for a Gaussian kernel.
struct HarmonicPlan {
    /// `(cos, sin)` of `2 pi j d / count` per slit `d`, for the lower and upper harmonic.
    tables: [Vec<(f32, f32)>; 2],
    /// Slit box and blur transfer at each harmonic (divided out: the separation accounts for
    /// them in the pattern itself).
    corrections: [f32; 2],
    /// Weight of the upper harmonic in the interpolation of `ln lambda` over `f^2`.
    upper_weight: f32,
    /// The lower harmonic is the mean (frequency 0, transfer 1 by definition).
    lower_is_mean: bool,
}

impl HarmonicPlan {
    fn new(count: usize, geometry: &SweepGeometry) -> Self {
        let w = f64::from(geometry.slit_width_px.max(1));
        let blur = f64::from(geometry.blur_px);
        let f = 1.0 / (2.0 * f64::from(geometry.stripe_px.max(1)));
        // Harmonic j has frequency j / (count w) cycles per projector px; the highest is Nyquist.
        let step = 1.0 / (count.max(1) as f64 * w);
        let top = (count / 2).max(1);
        let upper = ((f / step).ceil() as usize).clamp(1, top);
        let lower = upper - 1;
        let freq = |j: usize| j as f64 * step;
        let correction = |j: usize| {
            let arg = std::f64::consts::PI * w * freq(j);
            let sinc = if arg > 0.0 { arg.sin() / arg } else { 1.0 };
            (sinc * (-2.0 * (std::f64::consts::PI * blur * freq(j)).powi(2)).exp()) as f32
        };
        let table = |j: usize| {
            (0..count)
                .map(|d| {
                    let phase = std::f64::consts::TAU * (j * d) as f64 / count as f64;
                    (phase.cos() as f32, phase.sin() as f32)
                })
                .collect()
        };
        let (f_lo, f_hi) = (freq(lower), freq(upper));
        let upper_weight = if f_hi > f_lo {
            (((f * f - f_lo * f_lo) / (f_hi * f_hi - f_lo * f_lo)) as f32).clamp(0.0, 1.5)
        } else {
            1.0
        };
        Self {
            tables: [table(lower), table(upper)],
            corrections: [correction(lower), correction(upper)],
            upper_weight,
            lower_is_mean: lower == 0,
        }
    }

    /// The leak of one pixel and channel from its slit values less the black floor, `None`
    /// without light.
    fn leak(&self, q: impl Iterator<Item = f32>) -> Option<f32> {
        let (mut total, mut sums) = (0.0f32, [[0.0f32; 2]; 2]);
        for (d, v) in q.enumerate() {
            total += v;
            for (h, sum) in sums.iter_mut().enumerate() {
                let (c, s) = self.tables[h][d];
                sum[0] += v * c;
                sum[1] -= v * s;
            }
        }
        if total <= 0.0 || !total.is_finite() {
            return None;
        }
        let magnitude = |[re, im]: [f32; 2]| super::kernel_leak::phasor_magnitude(re, im);
        let transfer =
            |h: usize| (magnitude(sums[h]) / total / self.corrections[h]).clamp(1e-6, 1.0);
        let lower = if self.lower_is_mean { 1.0 } else { transfer(0) };
        let t = self.upper_weight;
        Some(
            ((1.0 - t) * lower.ln() + t * transfer(1).ln())
                .exp()
                .clamp(0.0, 1.0),
        )
    }
}

fn pixel_leak(
    slits: &[&[[f32; 3]]],
    white: &[[f32; 3]],
    i: usize,
    geometry: &SweepGeometry,
    reader: &Reader,
) -> ([f32; 3], Outcome) {
    let finite = slits
        .iter()
        .all(|s| s.get(i).is_some_and(|v| v.iter().all(|x| x.is_finite())));
    if !finite {
        return ([0.0; 3], Outcome::NoProfile);
    }
    // Only the cosine is read about the brightest slit; the harmonics do not depend on it.
    let brightest = match reader {
        Reader::Cosine(_) => {
            let sum = |j: usize| slits[j][i].iter().sum::<f32>();
            (0..slits.len())
                .max_by(|&a, &b| sum(a).total_cmp(&sum(b)))
                .unwrap_or(0)
        }
        Reader::Harmonics(_) => 0,
    };
    let b = geometry.black_level;
    let mut leak = [0.0f32; 3];
    let mut any = false;
    let mut flat = true;
    for c in 0..3 {
        let floor = b * white[i][c].max(0.0);
        let q = slits.iter().map(|s| (s[i][c] - floor).max(0.0));
        let Some(l) = reader.leak(q, brightest) else {
            continue;
        };
        any = true;
        flat &= l <= 1e-3;
        leak[c] = l;
    }
    match (any, flat) {
        (false, _) => ([0.0; 3], Outcome::NoProfile),
        (true, true) => (leak, Outcome::Wide),
        (true, false) => (leak, Outcome::Ok),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photometry::kernel_leak::gaussian_leak;

    /// Slit values of a pixel at projector column 0 whose response is a Gaussian kernel of sigma
    /// `sigma` (px) sampled by 1-px slits every `period` px (wrapped).
    fn gaussian_sweep(sigma: f64, period: usize) -> Vec<[f32; 3]> {
        sweep_of(|t| (-t * t / (2.0 * sigma * sigma)).exp(), period, 0.0)
    }

    /// Slit values of a pixel `offset` px from projector column 0 whose response along x is
    /// `kernel(distance)`, sampled by 1-px slits every `period` px (wrapped).
    fn sweep_of(kernel: impl Fn(f64) -> f64, period: usize, offset: f64) -> Vec<[f32; 3]> {
        (0..period)
            .map(|j| {
                let v: f64 = (-40..=40)
                    .map(|m| {
                        let x = j as f64 + (m * period as i64) as f64 - offset;
                        // The 1-px slit integrates the kernel over [x - 0.5, x + 0.5].
                        (0..10)
                            .map(|s| kernel(x - 0.45 + 0.1 * s as f64))
                            .sum::<f64>()
                            / 10.0
                    })
                    .sum();
                [v as f32; 3]
            })
            .collect()
    }

    fn leak_of(sweep: &[[f32; 3]], stripe_px: u32) -> f32 {
        let frames: Vec<Vec<[f32; 3]>> = sweep.iter().map(|v| vec![*v]).collect();
        let refs: Vec<&[[f32; 3]]> = frames.iter().map(|f| f.as_slice()).collect();
        let geometry = SweepGeometry {
            slit_width_px: 1,
            stripe_px,
            black_level: 0.0,
            blur_px: 0.0,
        };
        leak_from_slits(&refs, &[[1.0; 3]], &geometry, LeakReading::Harmonics).0[0][0]
    }

    #[test]
    fn a_pixel_between_two_slits_gets_the_same_leak() {
        // A narrow kernel (skin's green and blue core at the quick booth's scale) seen by pixels
        // at fractions of a slit from column 0: the harmonics' magnitudes do not depend on it
        // (a cosine about the brightest slit, the method before, read 0.68 instead of 0.76 at stripe 3
        // and offset 0.45, 0.39 instead of 0.55 at stripe 2 and offset 0.5).
        for stripe in [2, 3, 4] {
            let expected = gaussian_leak(0.7, stripe as f64) as f32;
            for offset in [0.0, 0.25, 0.45, 0.5] {
                let sweep = sweep_of(|t| (-t * t / (2.0 * 0.49)).exp(), 10, offset);
                let leak = leak_of(&sweep, stripe);
                assert!(
                    (leak - expected).abs() < 0.01,
                    "stripe {stripe}, offset {offset}: {leak} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn an_exponential_kernel_whose_tail_wraps_gets_close_to_its_analytic_leak() {
        // exp(-|d| / 2.5): 13 % of its light lies beyond the +-5 px of one slit period, which
        // wraps. ln(leak) is not linear in f^2 for this kernel, so the reading between
        // harmonics is approximate: within 0.03 of the analytic value (a cosine about the
        // brightest slit, the method before, read 0.05 for 0.13 at stripe 3).
        for stripe in [2, 3, 4] {
            let sweep = sweep_of(|t| (-t.abs() / 2.5).exp(), 10, 0.3);
            let expected = crate::photometry::kernel_leak::exponential_leak(2.5, stripe as f64);
            let leak = leak_of(&sweep, stripe);
            assert!(
                (f64::from(leak) - expected).abs() < 0.03,
                "stripe {stripe}: {leak} vs {expected}"
            );
        }
    }

    #[test]
    fn gaussian_kernel_gives_its_analytic_leak() {
        for sigma in [0.8, 1.2, 2.0] {
            let sweep = gaussian_sweep(sigma, 10);
            let frames: Vec<Vec<[f32; 3]>> = sweep.iter().map(|v| vec![*v]).collect();
            let refs: Vec<&[[f32; 3]]> = frames.iter().map(|f| f.as_slice()).collect();
            let geometry = SweepGeometry {
                slit_width_px: 1,
                stripe_px: 3,
                black_level: 0.0,
                blur_px: 0.0,
            };
            for reading in [LeakReading::Cosine, LeakReading::Harmonics] {
                let (leak, stats) = leak_from_slits(&refs, &[[1.0; 3]], &geometry, reading);
                let expected = gaussian_leak(sigma, 3.0) as f32;
                assert!(
                    (leak[0][0] - expected).abs() < 0.01,
                    "{reading:?}, sigma {sigma}: {} vs {expected}",
                    leak[0][0]
                );
                assert_eq!(stats.no_profile_pixels, 0);
                assert!(!stats.coarse_slits);
            }
        }
    }

    #[test]
    fn flat_dark_and_broken_profiles_are_counted_never_nan() {
        let flat = vec![vec![[0.1f32; 3]]; 10];
        let dark = vec![vec![[0.0f32; 3]]; 10];
        let mut broken = vec![vec![[0.2f32; 3]]; 10];
        broken[3][0] = [f32::NAN, 1.0, 1.0];
        let geometry = SweepGeometry {
            slit_width_px: 1,
            stripe_px: 3,
            black_level: 0.02,
            blur_px: 0.6,
        };
        for (frames, counts) in [(flat, Some((1, 0))), (dark, Some((0, 1))), (broken, None)] {
            let refs: Vec<&[[f32; 3]]> = frames.iter().map(|f| f.as_slice()).collect();
            for reading in [LeakReading::Cosine, LeakReading::Harmonics] {
                let (leak, stats) = leak_from_slits(&refs, &[[1.0; 3]], &geometry, reading);
                assert!(
                    leak[0]
                        .iter()
                        .all(|l| l.is_finite() && (0.0..=1.0).contains(l))
                );
                if let Some((wide, none)) = counts {
                    assert_eq!(stats.wide_kernel_pixels, wide);
                    assert_eq!(stats.no_profile_pixels, none);
                }
            }
        }
    }

    #[test]
    fn slits_as_wide_as_the_stripes_are_flagged_coarse() {
        let frames = vec![vec![[0.1f32; 3]]; 10];
        let refs: Vec<&[[f32; 3]]> = frames.iter().map(|f| f.as_slice()).collect();
        let geometry = SweepGeometry {
            slit_width_px: 3,
            stripe_px: 3,
            black_level: 0.0,
            blur_px: 0.0,
        };
        assert!(
            leak_from_slits(&refs, &[[1.0; 3]], &geometry, LeakReading::Cosine)
                .1
                .coarse_slits
        );
    }
}
