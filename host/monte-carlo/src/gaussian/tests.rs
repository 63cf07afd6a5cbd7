//! The deviates against independent truth: f64 Box-Muller of the same random bits (accuracy), and
//! the exact normal distribution (`libm::erfc`) for the statistics of millions of draws.

use super::*;
use crate::fast_math::for_each_drawn_uniform;
use crate::lane_rng::LaneRng;
use crate::photon_lanes::portable::{ln, next_bits, units_open};
use crate::simd::{F32s, U32s};

/// Deviates drawn by the statistical tests: 4.2 million, so that a frequency p is resolved to
/// sqrt(p / n) (5e-4 of the mean, 1e-4 of the 2-sigma tail).
const N: usize = 1 << 22;

fn draws(seed: u64, stream: u64, n: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; n];
    NormalStream::new(seed, stream).fill(&mut out);
    out
}

/// Standard normal CDF, from libm's erfc (accurate to about an f64 ulp).
fn phi(x: f64) -> f64 {
    0.5 * libm::erfc(-x / std::f64::consts::SQRT_2)
}

/// The exact Box-Muller deviates (cos part, sin part) of one lane's two draws, in f64: u as the
/// lanes map it (an f32, taken as exact), the angle from the same bits without rounding.
fn exact_pair(radial_bits: u32, angle_bits: u32) -> (f64, f64) {
    let u = f64::from(units_open(U32s::splat(radial_bits)).0[0]);
    let r = (-2.0 * u.ln()).sqrt();
    let a = (f64::from(angle_bits >> 9) / 8_388_608.0 - 0.5) * std::f64::consts::FRAC_PI_2;
    let (mut s, mut c) = a.sin_cos();
    if angle_bits & 1 != 0 {
        (c, s) = (-s, c);
    }
    if angle_bits & 2 != 0 {
        (c, s) = (-c, -s);
    }
    (r * c, r * s)
}

#[test]
fn deviates_are_box_muller_of_their_bits_within_the_stated_bound() {
    let mut stream = NormalStream::with_isa(5, 9, Isa::Portable);
    // The same lane streams, read as raw bits: each block is one radial and one angle draw.
    let mut bits = LaneRng::for_batch(5 ^ NORMAL_SEED_DOMAIN, 9);
    let (mut worst_abs, mut worst_rel) = (0.0f64, 0.0f64);
    let mut block = [0.0f32; BLOCK];
    for _ in 0..200_000 {
        stream.fill(&mut block);
        let radial = next_bits(&mut bits).0;
        let angle = next_bits(&mut bits).0;
        for lane in 0..LANES {
            let (c, s) = exact_pair(radial[lane], angle[lane]);
            for (got, want) in [(block[lane], c), (block[LANES + lane], s)] {
                let err = (f64::from(got) - want).abs();
                worst_abs = worst_abs.max(err);
                worst_rel = worst_rel.max(err / want.abs().max(1e-30));
            }
        }
    }
    eprintln!("worst error against f64 Box-Muller: {worst_abs:e} absolute, {worst_rel:e} relative");
    assert!(worst_abs < 2e-6, "worst absolute error {worst_abs:e}");
    assert!(worst_rel < 3e-7, "worst relative error {worst_rel:e}");
}

#[test]
fn the_radius_is_accurate_and_never_negative_for_every_uniform() {
    // r = sqrt(-2 ln u) for every f32 u in [1/2, 1] (the half of the draws with r < 1.18, where
    // an absolute error of `ln` would matter most), then a dense sweep down to the smallest u.
    let radius = |u: f32| (F32s::splat(-2.0) * ln(F32s::splat(u))).sqrt().0[0];
    let mut worst = 0.0f64;
    let mut check = |u: f32| {
        let got = radius(u);
        assert!(got >= 0.0, "radius {got} at u = {u:e}");
        let want = (-2.0 * f64::from(u).ln()).sqrt();
        if want > 0.0 {
            worst = worst.max((f64::from(got) - want).abs() / want);
        }
    };
    for_each_drawn_uniform(1_000_000, &mut check);
    eprintln!("worst relative error of the radius {worst:e}");
    assert!(worst < 1e-7, "worst relative error of the radius {worst:e}");
    assert_eq!(radius(1.0), 0.0);
    // The largest radius, from the smallest uniform (all 32 bits zero).
    let largest = f64::from(radius(units_open(U32s::splat(0)).0[0]));
    assert!((largest - (64.0 * std::f64::consts::LN_2).sqrt()).abs() < 1e-6);
    assert!(largest < 6.661, "{largest}");
}

#[test]
fn every_instruction_set_and_every_split_of_the_output_give_the_same_deviates() {
    let n = 10_000;
    let mut whole = vec![0.0f32; n];
    NormalStream::with_isa(3, 1, Isa::Portable).fill(&mut whole);
    let mut best = vec![0.0f32; n];
    NormalStream::new(3, 1).fill(&mut best);
    assert_eq!(whole, best, "{:?} against portable", Isa::detect());
    let mut pieces = vec![0.0f32; n];
    let mut stream = NormalStream::new(3, 1);
    let mut start = 0;
    for len in [1, 7, 31, 32, 33, 0, 64, 1000, 5].into_iter().cycle() {
        let end = (start + len).min(n);
        stream.fill(&mut pieces[start..end]);
        start = end;
        if start == n {
            break;
        }
    }
    assert_eq!(whole, pieces);
    assert_ne!(draws(3, 1, 64), draws(3, 2, 64));
    assert_ne!(draws(3, 1, 64), draws(4, 1, 64));
}

/// Mean, variance and excess kurtosis within 5 standard errors of the normal's 0, 1 and 0.
#[test]
fn the_moments_are_the_standard_normals() {
    let z = draws(11, 3, N);
    let n = N as f64;
    let mean = z.iter().map(|&x| f64::from(x)).sum::<f64>() / n;
    let var = z
        .iter()
        .map(|&x| (f64::from(x) - mean).powi(2))
        .sum::<f64>()
        / n;
    let kurt = z.iter().map(|&x| f64::from(x).powi(4)).sum::<f64>() / n - 3.0;
    eprintln!(
        "mean {mean:.2e} (se {:.1e}), variance {var:.6} (se {:.1e}), excess kurtosis {kurt:.2e} (se {:.1e})",
        1.0 / n.sqrt(),
        (2.0 / n).sqrt(),
        (24.0 / n).sqrt()
    );
    assert!(mean.abs() < 5.0 / n.sqrt(), "mean {mean}");
    assert!((var - 1.0).abs() < 5.0 * (2.0 / n).sqrt(), "variance {var}");
    assert!(
        kurt.abs() < 5.0 * (24.0 / n).sqrt(),
        "excess kurtosis {kurt}"
    );
}

/// Pearson correlation of `a` and `b` (means and variances taken as the normal's 0 and 1).
fn correlation(a: &[f32], b: &[f32], f: impl Fn(f32) -> f64, mean: f64, var: f64) -> f64 {
    let pairs = a.len().min(b.len()) as f64;
    a.iter()
        .zip(b)
        .map(|(&x, &y)| (f(x) - mean) * (f(y) - mean))
        .sum::<f64>()
        / pairs
        / var
}

/// Neighbours (lag 1), a lane's cos and sin parts (lag `LANES`), a lane's consecutive pairs
/// (lag `BLOCK`), and the same positions of other streams and seeds (the next frame's noise, the
/// next calibration pose's) are uncorrelated, in the values and in their squares (the squares
/// catch a shared radius, which leaves the values themselves uncorrelated): |r| below 5 / sqrt(n).
#[test]
fn neighbours_and_other_streams_are_uncorrelated() {
    let z = draws(11, 3, N);
    let limit = 5.0 / (N as f64).sqrt();
    let value = |x: f32| f64::from(x);
    let square = |x: f32| f64::from(x).powi(2);
    let others = [
        ("next stream", draws(11, 4, N)),
        ("next seed", draws(12, 3, N)),
        ("pose seed", draws(1011, 3, N)),
    ];
    for lag in [1, LANES, BLOCK] {
        let r = correlation(&z, &z[lag..], value, 0.0, 1.0);
        let r2 = correlation(&z, &z[lag..], square, 1.0, 2.0);
        eprintln!("lag {lag}: r {r:.2e}, squares {r2:.2e} (limit {limit:.1e})");
        assert!(r.abs() < limit, "lag {lag}: correlation {r}");
        assert!(r2.abs() < limit, "lag {lag}: correlation of squares {r2}");
    }
    for (name, other) in &others {
        let r = correlation(&z, other, value, 0.0, 1.0);
        let r2 = correlation(&z, other, square, 1.0, 2.0);
        eprintln!("{name}: r {r:.2e}, squares {r2:.2e}");
        assert!(r.abs() < limit, "{name}: correlation {r}");
        assert!(r2.abs() < limit, "{name}: correlation of squares {r2}");
    }
}

/// Kolmogorov's limiting distribution: P(sqrt(n) D > lambda).
fn kolmogorov_p(lambda: f64) -> f64 {
    (1..100)
        .map(|k| {
            let k = f64::from(k);
            2.0 * (-1f64).powf(k - 1.0) * (-2.0 * k * k * lambda * lambda).exp()
        })
        .sum::<f64>()
        .clamp(0.0, 1.0)
}

/// The Kolmogorov-Smirnov distance to the exact normal CDF, a chi-square over 0.05-wide bins of
/// [-5, 5] plus the two tails (202 bins), and the frequencies beyond 2, 3 and 4 sigma: each
/// accepted unless a true normal sample would do worse once in 1000 (the chi-square: once in
/// 10^4, its bins' expectations from the exact CDF too).
#[test]
fn the_distribution_is_the_normals() {
    let mut z = draws(23, 7, N);
    let n = N as f64;
    z.sort_unstable_by(f32::total_cmp);
    let d = z
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            let f = phi(f64::from(x));
            (f - i as f64 / n).abs().max((i + 1) as f64 / n - f)
        })
        .fold(0.0, f64::max);
    let p_ks = kolmogorov_p(n.sqrt() * d);
    eprintln!(
        "KS distance {d:.2e} (sqrt(n) D = {:.3}), p {p_ks:.3}",
        n.sqrt() * d
    );
    assert!(p_ks > 1e-3, "KS distance {d:e}, p {p_ks:e}");

    let width = 0.05;
    let bins = 200;
    let mut counts = vec![0u64; bins + 2];
    for &x in &z {
        let b = ((f64::from(x) + 5.0) / width).floor();
        counts[(b.clamp(-1.0, bins as f64) + 1.0) as usize] += 1;
    }
    let edge = |b: usize| -5.0 + width * b as f64;
    let chi2: f64 = (0..bins + 2)
        .map(|i| {
            let lo = if i == 0 { 0.0 } else { phi(edge(i - 1)) };
            let hi = if i == bins + 1 { 1.0 } else { phi(edge(i)) };
            let expected = n * (hi - lo);
            (counts[i] as f64 - expected).powi(2) / expected
        })
        .sum();
    // 201 degrees of freedom: the chi-square's 1 - 1e-4 quantile is 201 + 3.72 sqrt(402) + ... =
    // 285 (Wilson-Hilferty).
    let dof = (bins + 1) as f64;
    let wh = dof * (1.0 - 2.0 / (9.0 * dof) + 3.719 * (2.0 / (9.0 * dof)).sqrt()).powi(3);
    eprintln!("chi-square {chi2:.1} over {dof} degrees of freedom (limit {wh:.1})");
    assert!(
        chi2 < wh,
        "chi-square {chi2} over {dof} degrees of freedom (limit {wh})"
    );

    for k in [2.0, 3.0, 4.0] {
        let beyond = z.iter().filter(|&&x| f64::from(x).abs() > k).count() as f64;
        let p = 2.0 * phi(-k);
        let se = (n * p * (1.0 - p)).sqrt();
        // 3.29 standard errors: two-sided 1e-3.
        eprintln!(
            "beyond {k} sigma: {beyond} against {:.1} (se {se:.1})",
            n * p
        );
        assert!(
            (beyond - n * p).abs() < 3.29 * se,
            "beyond {k} sigma: {beyond} against {}",
            n * p
        );
    }
    assert!(z[0] > -6.661 && z[N - 1] < 6.661);
}
