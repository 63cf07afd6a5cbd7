//! Branch-free `ln`, `sin` and `cos` for the photon lanes, in f32: the constants and error bounds
//! here, the lane-vector code in `lane_kernels.rs` (compiled once per instruction set).
//!
//! `std`'s `f32::ln` and `sin_cos` call into libm, which the compiler cannot vectorise; these
//! versions are straight-line code (bit manipulation and polynomials with fused multiply-adds, no
//! division) that it turns
//! into SIMD over 16 lanes. They use the Cephes single-precision polynomials (Moshier 1984-2000,
//! `logf.c`, `sinf.c`; freely usable), without the special-case branches the transport never
//! needs.
//!
//! Error bounds (checked by the tests below against `f64`'s `ln`, `sin`, `cos` on dense sweeps):
//! - `ln`: absolute error below 1.2e-7 on [1/2, 2] (ln there is below 0.7) and relative error
//!   below 1.5e-7 (1.3 f32 epsilons) elsewhere, for every positive normal `x`. The transport
//!   samples a step as -ln(u), u in (0, 1]: its error is then below 1.5e-7 relative for steps above
//!   0.7 optical depths and 1.2e-7 absolute below (0.1 parts per million of a mean free path).
//! - `sin_cos_quarter`: absolute error below 1.2e-7 for |a| <= pi/4.
//!
//! Why f32 is enough for the walk: every quantity the lanes carry is O(1) in its units (mm,
//! direction cosines, weights >= 1e-5 of roulette), f32 resolves 6e-8 of each; positions within a
//! 10 mm medium to 1e-6 mm. MCML's GPU port (Alerstam et al.; Lo et al., GPU-MCML) runs in f32.
//! Sums that grow (per-layer absorption over a photon's ~1,300 events, the tallies) are kept in
//! f64. A photon's deposit in a layer is the exact (f64) difference of its f32 weights, so the
//! deposits add up to the weight lost exactly; each interaction's f32 rounding of the weight
//! (6e-8 relative, unbiased) moves a deposit by at most 6e-8 of the weight, far below the
//! per-layer standard error of any run. The tests in `photon_lanes` and `transport` check the lanes against analytic
//! answers and the race (`benches/mcml_race.py`) against MCML within 3 standard errors.
//!
//! They work on whole lane vectors. Neither handles zero, infinities, NaN or subnormals; the
//! callers never pass them.

// The constants are quoted digit for digit as Cephes publishes them, so they can be checked.
#![allow(clippy::excessive_precision)]

/// ln(2) split so that `k * LN2_HI` is exact for every f32 exponent (Cephes' C1, C2).
pub(crate) const LN2_HI: f32 = 0.693_359_375;
pub(crate) const LN2_LO: f32 = -2.121_944_40e-4;
/// Coefficients of P(f) with ln(1 + f) ~ f - f^2 / 2 + f^3 P(f), constant term first (Cephes).
pub(crate) const LN_POLY: [f32; 9] = [
    3.333_333_117_4e-1,
    -2.499_999_399_3e-1,
    2.000_071_476_5e-1,
    -1.666_805_766_5e-1,
    1.424_932_278_7e-1,
    -1.242_014_084_6e-1,
    1.167_699_874_0e-1,
    -1.151_461_031_0e-1,
    7.037_683_629_2e-2,
];
/// sin a ~ a + a z S(z), z = a^2, highest degree first (Cephes `sinf`).
pub(crate) const SIN_POLY: [f32; 3] =
    [-1.951_529_589_1e-4, 8.332_160_873_6e-3, -1.666_665_461_1e-1];
/// cos a ~ 1 - z / 2 + z^2 C(z), highest degree first (Cephes `cosf`).
pub(crate) const COS_POLY: [f32; 3] = [
    2.443_315_711_809_948e-5,
    -1.388_731_625_493_765e-3,
    4.166_664_568_298_827e-2,
];
pub(crate) const TWO_POW_M31: f32 = 1.0 / 2_147_483_648.0;
pub(crate) const TWO_POW_M32: f32 = 1.0 / 4_294_967_296.0;

/// Visits the uniforms the lanes draw, which lie in [2^-32, 1]: every f32 in [1/2, 1] (2^23 of
/// them, the steps below 0.7 optical depths), then `steps + 1` points of a geometric sweep from 1
/// down to 2^-32. For the accuracy tests of what is computed from a uniform (`ln`, the normal
/// deviates' radius).
#[cfg(test)]
pub(crate) fn for_each_drawn_uniform(steps: u32, mut visit: impl FnMut(f32)) {
    let mut x = 0.5f32;
    while x <= 1.0 {
        visit(x);
        x = f32::from_bits(x.to_bits() + 1);
    }
    for i in 0..=steps {
        visit(2f32.powf(-32.0 * i as f32 / steps as f32));
    }
}

#[cfg(test)]
mod tests {
    use super::for_each_drawn_uniform;
    use crate::photon_lanes::portable::{ln, sin_cos_quarter};
    use crate::simd::{F32s, LANES};

    fn ln1(x: f32) -> f32 {
        ln(F32s::splat(x)).0[LANES - 1]
    }

    fn sin_cos1(a: f32) -> (f32, f32) {
        let (s, c) = sin_cos_quarter(F32s::splat(a));
        (s.0[0], c.0[0])
    }

    /// The error of `ln` at x against f64's ln: absolute on [1/2, 2], relative elsewhere.
    fn ln_error(x: f32) -> (f64, f64) {
        let want = f64::from(x).ln();
        let err = (f64::from(ln1(x)) - want).abs();
        if (0.5..=2.0).contains(&x) {
            (err, 0.0)
        } else {
            (0.0, err / want.abs())
        }
    }

    #[test]
    fn ln_is_within_its_stated_bounds_on_the_unit_interval_and_beyond() {
        let (mut worst_abs, mut worst_rel) = (0.0f64, 0.0f64);
        let mut check = |x: f32| {
            let (a, r) = ln_error(x);
            worst_abs = worst_abs.max(a);
            worst_rel = worst_rel.max(r);
        };
        for_each_drawn_uniform(400_000, &mut check);
        // And a linear sweep of [1/2, 2], the interval of the stated bounds.
        for i in 0..=400_000u32 {
            check(0.5 + 1.5 * i as f32 / 400_000.0);
        }
        for e in -125..127 {
            check(1.37 * 2f32.powi(e));
            check(1.999_999 * 2f32.powi(e));
        }
        assert!(
            worst_abs < 1.2e-7,
            "worst absolute error on [1/2, 2] {worst_abs:e}"
        );
        assert!(
            worst_rel < 1.5e-7,
            "worst relative error elsewhere {worst_rel:e}"
        );
        assert_eq!(ln1(1.0), 0.0);
        let mixed: [f32; LANES] = std::array::from_fn(|i| 0.37 * 3f32.powi(i as i32 - 8));
        for (got, x) in ln(F32s(mixed)).0.iter().zip(mixed) {
            assert!(
                (f64::from(*got) - f64::from(x).ln()).abs()
                    < 1.5e-7 * f64::from(x).ln().abs().max(1.0)
            );
        }
    }

    #[test]
    fn sin_cos_is_within_its_stated_bound_on_a_quarter_turn() {
        let mut worst: f64 = 0.0;
        let quarter = std::f64::consts::FRAC_PI_4;
        for i in 0..=400_000 {
            let a = (-quarter + 2.0 * quarter * f64::from(i) / 400_000.0) as f32;
            let (s, c) = sin_cos1(a);
            let a = f64::from(a);
            worst = worst
                .max((f64::from(s) - a.sin()).abs())
                .max((f64::from(c) - a.cos()).abs());
        }
        assert!(worst < 1.2e-7, "worst absolute error {worst:e}");
    }
}
