//! Each pixel's kernel leak at the stripe frequency, measured from the slit sweep (the input of
//! [`super::kernel_leak`]).
//!
//! The slit frames along x light one line of projector columns at a time, stepping by the slit
//! width over the slit period; a camera pixel's values over the sweep sample its response to a
//! line of light against the line's distance: the subsurface kernel along x (blurred by the
//! projector and the slit's width), plus the direct reflection in the slit that lands on it.
//! The leak is that profile's normalised transfer at the stripe frequency `f = 1 / (2 stripe)`:
//!
//! `lambda = sum_d q(d) cos(2 pi f x_d) / (sum_d q(d) sinc(w f) exp(-2 pi^2 s^2 f^2))`,
//!
//! over the slits `d` (distance `x_d = d w` px from the brightest, wrapped into one period), with
//! `q` the slit value less the black-level light (`b` times the white frame), `w` the slit
//! width and `s` the projector blur (the `sinc` undoes the slit's own box, the exponential the
//! blur, which the separation accounts for in the pattern itself).
//!
//! What it cannot see, and how that shows:
//! - The direct reflection sits in the brightest slit as if it were kernel; it is a few percent of
//!   skin's light, so it raises `lambda` by about `Ld / T`, which the separation then treats as
//!   global (a small, known underestimate of the direct part).
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

/// Leak per pixel and channel from the slit frames of one axis (`slits[j]` the frame of offset
/// `j * slit_width`, row-major RGB) and the white frame `white` (same units).
pub fn leak_from_slits(
    slits: &[&[[f32; 3]]],
    white: &[[f32; 3]],
    geometry: &SweepGeometry,
) -> (Vec<[f32; 3]>, SlitLeakStats) {
    let n = white.len();
    let mut stats = SlitLeakStats {
        pixels: n as u64,
        coarse_slits: geometry.slit_width_px >= geometry.stripe_px,
        ..Default::default()
    };
    let weights = slit_weights(slits.len(), geometry);
    let measured: Vec<([f32; 3], Outcome)> = (0..n)
        .into_par_iter()
        .map(|i| pixel_leak(slits, white, i, geometry, &weights))
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

/// `cos(2 pi f x_d) / sinc(w f)` for each wrapped slit distance `d` (index = distance mod the
/// number of slits).
fn slit_weights(count: usize, geometry: &SweepGeometry) -> Vec<f32> {
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

fn pixel_leak(
    slits: &[&[[f32; 3]]],
    white: &[[f32; 3]],
    i: usize,
    geometry: &SweepGeometry,
    weights: &[f32],
) -> ([f32; 3], Outcome) {
    let count = slits.len();
    let brightest = (0..count)
        .filter(|&j| {
            slits[j]
                .get(i)
                .is_some_and(|v| v.iter().all(|x| x.is_finite()))
        })
        .max_by(|&a, &b| {
            let sum = |j: usize| slits[j][i].iter().sum::<f32>();
            sum(a).total_cmp(&sum(b))
        });
    let Some(brightest) = brightest else {
        return ([0.0; 3], Outcome::NoProfile);
    };
    let b = geometry.black_level;
    let mut leak = [0.0f32; 3];
    let mut any = false;
    let mut flat = true;
    for c in 0..3 {
        let floor = b * white[i][c].max(0.0);
        let (mut total, mut weighted) = (0.0f32, 0.0f32);
        for (j, slit) in slits.iter().enumerate() {
            let q = (slit[i][c] - floor).max(0.0);
            total += q;
            weighted += q * weights[(j + count - brightest) % count];
        }
        if total <= 0.0 || !total.is_finite() || !weighted.is_finite() {
            continue;
        }
        any = true;
        let l = (weighted / total).clamp(0.0, 1.0);
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
        (0..period)
            .map(|j| {
                let v: f64 = (-20..=20)
                    .map(|m| {
                        let x = j as f64 + (m * period as i64) as f64;
                        // The 1-px slit integrates the kernel over [x - 0.5, x + 0.5].
                        (0..10)
                            .map(|s| {
                                let t = x - 0.45 + 0.1 * s as f64;
                                (-t * t / (2.0 * sigma * sigma)).exp()
                            })
                            .sum::<f64>()
                            / 10.0
                    })
                    .sum();
                [v as f32; 3]
            })
            .collect()
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
            let (leak, stats) = leak_from_slits(&refs, &[[1.0; 3]], &geometry);
            let expected = gaussian_leak(sigma, 3.0) as f32;
            assert!(
                (leak[0][0] - expected).abs() < 0.01,
                "sigma {sigma}: {} vs {expected}",
                leak[0][0]
            );
            assert_eq!(stats.no_profile_pixels, 0);
            assert!(!stats.coarse_slits);
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
            let (leak, stats) = leak_from_slits(&refs, &[[1.0; 3]], &geometry);
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
            leak_from_slits(&refs, &[[1.0; 3]], &geometry)
                .1
                .coarse_slits
        );
    }
}
